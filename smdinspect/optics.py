"""Thin-lens optics of a shape-from-focus rig: blur, magnification, depth of field, sweeps.

The relations of the source paper (Nayar & Nakagawa, *Shape from Focus*):

* thin lens: ``1/f = 1/u + 1/v`` (``f`` focal length, ``u`` object distance, ``v`` lens to
  sensor distance);
* blur circle of a point at distance ``u`` imaged with the sensor at ``v`` (aperture
  diameter ``D``): ``C = D·v·(1/f − 1/u − 1/v)`` (on the sensor; we use ``|C|``);
* Gaussian point-spread function with ``σ = k·C``;
* moving camera: the focused plane of frame ``n`` lies at height
  ``h_n = d − (d_f + n·Δd)`` above the base, with ``d`` the lens's start height above the
  base, ``d_f`` the working distance (lens to focused plane, ``u`` of the focused plane) and
  ``Δd`` the step.

Geometry used throughout smdinspect: the camera looks down along −z; ``z_mm`` is the height
of a frame's focused plane above the board (base) plane; ``height_mm`` is the height of a
surface point above the same plane. In the frame focused at ``z_mm`` the lens sits at
height ``z_mm + d_f`` and a point at ``height_mm`` is at object distance
``u = d_f + z_mm − height_mm``: points above the focused plane (``height_mm > z_mm``) are
nearer to the lens.

Blur is expressed in object-space pixels of size ``pixel_size_mm = pixel_pitch_mm / m``
(``m`` the magnification of the focused plane), which for a moving camera is the same in
every frame. A telecentric lens keeps the magnification of every plane at ``m``; an
ordinary (entocentric) lens images a point at distance ``u`` with ``m(u) = v/u``, so
surfaces away from the focused plane change size from frame to frame
(:meth:`Optics.magnification_at`, :meth:`Optics.scale_at`).

Examples
--------
>>> from smdinspect.optics import Optics
>>> o = Optics()
>>> round(o.pixel_size_mm, 4), round(o.working_distance_mm, 1)
(0.015, 100.0)
>>> bool(o.blur_sigma_px(0.05, 0.0) > o.blur_sigma_px(0.0, 0.0))
True
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from .errors import InputError

__all__ = [
    "Optics",
    "SweepPlan",
    "blur_circle_mm",
    "focus_height_mm",
    "gaussian_psf",
    "image_distance_mm",
    "recommend_sweep",
]


def image_distance_mm(focal_length_mm: float, object_distance_mm: float) -> float:
    """Solve the thin-lens law ``1/f = 1/u + 1/v`` for ``v``.

    Parameters
    ----------
    focal_length_mm : float
        ``f > 0``.
    object_distance_mm : float
        ``u > f`` (a real image).

    Returns
    -------
    float
        ``v = 1 / (1/f − 1/u)`` in mm.

    Examples
    --------
    >>> image_distance_mm(50.0, 100.0)
    100.0
    """
    f = _positive(focal_length_mm, "focal_length_mm")
    u = _positive(object_distance_mm, "object_distance_mm")
    if u <= f:
        raise InputError(
            f"object_distance_mm must be > focal_length_mm ({f}) for a real image; got {u}"
        )
    return 1.0 / (1.0 / f - 1.0 / u)


def blur_circle_mm(
    object_distance_mm,
    *,
    focal_length_mm: float,
    aperture_mm: float,
    sensor_distance_mm: float,
) -> np.ndarray:
    """Diameter of the blur circle on the sensor, ``|C| = |D·v·(1/f − 1/u − 1/v)|``.

    Parameters
    ----------
    object_distance_mm : float or array
        ``u``, distance of the point from the lens (mm, > 0).
    focal_length_mm, aperture_mm, sensor_distance_mm : float
        ``f``, ``D`` and ``v`` (mm).

    Returns
    -------
    ndarray of float64, shape of ``object_distance_mm``
        ``|C|`` in mm on the sensor; 0 for the point ``u`` focused at ``v``.
    """
    f = _positive(focal_length_mm, "focal_length_mm")
    d = _positive(aperture_mm, "aperture_mm")
    v = _positive(sensor_distance_mm, "sensor_distance_mm")
    u = np.asarray(object_distance_mm, dtype=np.float64)
    if np.any(~np.isfinite(u)) or np.any(u <= 0):
        raise InputError("object_distance_mm must be finite and > 0 everywhere")
    return np.abs(d * v * (1.0 / f - 1.0 / u - 1.0 / v))


def focus_height_mm(n, *, d_mm: float, d_f_mm: float, step_mm: float) -> np.ndarray:
    """Height of the focused plane of frame ``n``: ``h_n = d − (d_f + n·Δd)``.

    Parameters
    ----------
    n : int or array of int
        Frame index (0 for the first frame).
    d_mm : float
        Height of the lens above the base plane at frame 0.
    d_f_mm : float
        Working distance, lens to focused plane.
    step_mm : float
        ``Δd``, how far the camera moves towards the base between frames (negative when
        it moves away).

    Returns
    -------
    ndarray of float64
        ``h_n`` in mm, shape of ``n``.

    Examples
    --------
    >>> round(float(focus_height_mm(2, d_mm=101.0, d_f_mm=100.0, step_mm=0.05)), 6)
    0.9
    """
    for name, value in (("d_mm", d_mm), ("d_f_mm", d_f_mm), ("step_mm", step_mm)):
        _finite(value, name)
    n = np.asarray(n, dtype=np.float64)
    return d_mm - (d_f_mm + n * step_mm)


def gaussian_psf(sigma_px: float, *, radius_px: int | None = None) -> np.ndarray:
    """Sampled 2D Gaussian point-spread function, normalised to sum to 1.

    Parameters
    ----------
    sigma_px : float
        Standard deviation in pixels (>= 0; 0 gives a single 1).
    radius_px : int, optional
        Half size of the kernel; default ``ceil(4σ)``.

    Returns
    -------
    (2r+1, 2r+1) float64
    """
    s = _finite(sigma_px, "sigma_px")
    if s < 0:
        raise InputError(f"sigma_px must be >= 0; got {s}")
    r = int(math.ceil(4 * s)) if radius_px is None else int(radius_px)
    if r < 0:
        raise InputError(f"radius_px must be >= 0; got {radius_px}")
    if s == 0 or r == 0:
        k = np.zeros((2 * r + 1, 2 * r + 1))
        k[r, r] = 1.0
        return k
    x = np.arange(-r, r + 1, dtype=np.float64)
    g = np.exp(-(x**2) / (2 * s * s))
    k = np.outer(g, g)
    return k / k.sum()


@dataclass(frozen=True)
class Optics:
    """A camera + lens for shape from focus, with thin-lens defocus.

    Parameters
    ----------
    focal_length_mm : float
        ``f`` of the (thin) lens.
    magnification : float
        ``m = v / d_f`` of the focused plane (sensor size / object size).
    aperture_mm : float
        ``D``, entrance-pupil diameter.
    pixel_pitch_mm : float
        Sensor pixel pitch. Object-space pixel size is ``pixel_pitch_mm / magnification``.
    k : float
        ``σ = k·C``. The default ``1/(2√2)`` is Pentland's ``σ = r/√2`` for a blur circle
        of radius ``r``; a uniform disc of diameter ``C`` would give ``C/4``.
    telecentric : bool
        True: constant magnification for every height (object-side telecentric lens).
        False: an ordinary lens, whose magnification ``v/u`` changes with distance.
    sigma0_px : float
        In-focus blur (lens aberrations, pixel aperture) added in quadrature:
        ``σ = sqrt(sigma0² + (k·C/pitch)²)``.

    Notes
    -----
    The default is a ~15 µm/px, deliberately shallow set-up: a 50 mm lens at 1:1
    (``d_f = v = 100 mm``) with a 50 mm pupil (f/1, object-side NA ≈ 0.24) on a sensor with
    15 µm pixels. One Δd = 0.05 mm of defocus grows σ by ≈ 0.59 px and the depth of field
    (blur circle ≤ 1 px) is ≈ 0.06 mm, so a focus peak spans several 0.05 mm frames.
    Typical machine-vision optics at 15 µm/px have far more depth of field; use
    :func:`recommend_sweep` to choose their step.

    Examples
    --------
    >>> o = Optics()
    >>> round(float(o.blur_sigma_px(0.05, 0.0)), 2)
    0.66
    """

    focal_length_mm: float = 50.0
    magnification: float = 1.0
    aperture_mm: float = 50.0
    pixel_pitch_mm: float = 0.015
    k: float = 1.0 / (2.0 * math.sqrt(2.0))
    telecentric: bool = True
    sigma0_px: float = 0.3

    def __post_init__(self) -> None:
        for name in ("focal_length_mm", "magnification", "aperture_mm", "pixel_pitch_mm", "k"):
            _positive(getattr(self, name), name)
        s0 = _finite(self.sigma0_px, "sigma0_px")
        if s0 < 0:
            raise InputError(f"sigma0_px must be >= 0; got {s0}")
        if not isinstance(self.telecentric, (bool, np.bool_)):
            raise InputError(f"telecentric must be True or False; got {self.telecentric!r}")

    # -- derived geometry -----------------------------------------------------------
    @property
    def sensor_distance_mm(self) -> float:
        """``v = f·(1 + m)``, lens to sensor."""
        return self.focal_length_mm * (1.0 + self.magnification)

    @property
    def working_distance_mm(self) -> float:
        """``d_f = f·(1 + 1/m)``, lens to focused plane (the ``u`` that is in focus)."""
        return self.focal_length_mm * (1.0 + 1.0 / self.magnification)

    @property
    def pixel_size_mm(self) -> float:
        """Object-space size of one pixel in the focused plane."""
        return self.pixel_pitch_mm / self.magnification

    @property
    def f_number(self) -> float:
        """``N = f / D``."""
        return self.focal_length_mm / self.aperture_mm

    def object_distance_mm(self, height_mm, z_mm) -> np.ndarray:
        """``u = d_f + z − h`` of points at ``height_mm`` in the frame focused at ``z_mm``."""
        h = np.asarray(height_mm, dtype=np.float64)
        z = np.asarray(z_mm, dtype=np.float64)
        u = self.working_distance_mm + z - h
        if np.any(~np.isfinite(u)):
            raise InputError("height_mm and z_mm must be finite")
        if np.any(u <= self.focal_length_mm):
            worst = float(np.max(h - z))
            raise InputError(
                f"a point {worst:.3f} mm above the focused plane is inside the focal length "
                f"(working distance {self.working_distance_mm:.1f} mm); check height_mm/z_mm"
            )
        return u

    # -- blur -----------------------------------------------------------------------
    def blur_circle_mm(self, height_mm, z_mm) -> np.ndarray:
        """``|C|`` on the sensor (mm) for points at ``height_mm`` in the frame at ``z_mm``."""
        u = self.object_distance_mm(height_mm, z_mm)
        return blur_circle_mm(
            u,
            focal_length_mm=self.focal_length_mm,
            aperture_mm=self.aperture_mm,
            sensor_distance_mm=self.sensor_distance_mm,
        )

    def blur_sigma_px(self, height_mm, z_mm) -> np.ndarray:
        """Gaussian PSF σ in pixels for points at ``height_mm`` seen in the frame at ``z_mm``.

        ``σ = sqrt(sigma0_px² + (k·|C| / pixel_pitch_mm)²)``; a sensor pixel is one
        object-space pixel of size :attr:`pixel_size_mm`.

        Parameters
        ----------
        height_mm : float or (…) array
            Surface height above the base plane (mm).
        z_mm : float or array broadcastable with ``height_mm``
            Height of the focused plane (mm).

        Returns
        -------
        ndarray of float64, broadcast shape
        """
        c_px = self.k * self.blur_circle_mm(height_mm, z_mm) / self.pixel_pitch_mm
        return np.sqrt(self.sigma0_px**2 + c_px**2)

    def blur_rate_px_per_mm(self) -> float:
        """``dσ/d|h − z|`` far from the in-focus floor (px of σ per mm of defocus).

        Evaluated symmetrically at ±0.1 mm; equals ``k·D·v / (d_f²·pitch)`` to first order.
        """
        c_px = self.k * self.blur_circle_mm(np.array([-0.1, 0.1]), 0.0) / self.pixel_pitch_mm
        return float(np.mean(c_px) / 0.1)

    # -- magnification ----------------------------------------------------------------
    def magnification_at(self, height_mm, z_mm) -> np.ndarray:
        """Magnification of points at ``height_mm`` in the frame focused at ``z_mm``.

        Telecentric: ``m`` everywhere. Ordinary lens: ``v / u = v / (d_f + z − h)``, which
        is ``m`` on the focused plane, larger above it, smaller below it.
        """
        u = self.object_distance_mm(height_mm, z_mm)
        if self.telecentric:
            return np.full(np.shape(u), self.magnification, dtype=np.float64)
        return self.sensor_distance_mm / u

    def scale_at(self, height_mm, z_mm) -> np.ndarray:
        """Image scale of points at ``height_mm`` relative to the focused plane (1 = same)."""
        return self.magnification_at(height_mm, z_mm) / self.magnification

    # -- depth of field ---------------------------------------------------------------
    def depth_of_field_mm(self, *, coc_px: float = 1.0) -> float:
        """Total depth (near + far) over which the blur circle is ≤ ``coc_px`` pixels.

        Exact thin-lens limits: ``|1/d_f − 1/u| ≤ c / (D·v)`` with ``c = coc_px·pitch``.
        Returns ``inf`` when the far limit is at infinity.
        """
        c = _positive(coc_px, "coc_px") * self.pixel_pitch_mm
        e = c / (self.aperture_mm * self.sensor_distance_mm)
        inv = 1.0 / self.working_distance_mm
        u_near = 1.0 / (inv + e)
        if e >= inv:
            return math.inf
        u_far = 1.0 / (inv - e)
        return u_far - u_near

    # -- serialisation ------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """Plain dict for ``stack.json``'s optics block (fields + derived values)."""
        doc = asdict(self)
        doc.update(
            model="thin_lens_gaussian",
            sensor_distance_mm=self.sensor_distance_mm,
            working_distance_mm=self.working_distance_mm,
            pixel_size_mm=self.pixel_size_mm,
            depth_of_field_mm=self.depth_of_field_mm(),
        )
        return doc

    @classmethod
    def from_dict(cls, doc: dict[str, Any]) -> "Optics":
        """Inverse of :meth:`to_dict` (derived and unknown keys are ignored)."""
        if not isinstance(doc, dict):
            raise InputError(f"optics must be a JSON object; got {type(doc).__name__}")
        names = {f for f in cls.__dataclass_fields__}
        return cls(**{k: v for k, v in doc.items() if k in names})

    @classmethod
    def for_pixel_size(cls, pixel_size_mm: float, **kwargs: Any) -> "Optics":
        """The default optics with the magnification set to give ``pixel_size_mm``.

        Unless ``aperture_mm`` is given, the pupil is scaled so the object-side cone
        ``D / d_f`` (and so the blur in mm per mm of defocus and the depth of field in mm)
        stays that of the default; the blur in pixels then scales with ``1/pixel_size_mm``.
        """
        p = _positive(pixel_size_mm, "pixel_size_mm")
        base = cls(**kwargs)
        m = base.pixel_pitch_mm / p
        # keep the object-side cone angle D/d_f, so blur in mm per mm of defocus is unchanged
        cone = base.aperture_mm / base.working_distance_mm
        d_f = base.focal_length_mm * (1.0 + 1.0 / m)
        if "aperture_mm" in kwargs:
            return cls(**{**kwargs, "magnification": m})
        return cls(**{**kwargs, "magnification": m, "aperture_mm": cone * d_f})


@dataclass(frozen=True)
class SweepPlan:
    """A recommended z sweep (see :func:`recommend_sweep`).

    Attributes
    ----------
    step_mm : float
        Δd between frames.
    n_frames : int
    z_mm : (n_frames,) float64
        Focused-plane heights, ascending, covering the height range plus margins.
    focus_sigma_mm : float
        Predicted width σ_F of the focus curve (Gaussian in z).
    depth_of_field_mm : float
        Depth of field (blur circle ≤ 1 px) of the optics.
    """

    step_mm: float
    n_frames: int
    z_mm: np.ndarray
    focus_sigma_mm: float
    depth_of_field_mm: float


def recommend_sweep(
    optics: Optics,
    height_range_mm: tuple[float, float],
    *,
    texture_cyc_px: float = 0.2,
    frames_per_sigma: float = 1.0,
    margin_frames: int = 3,
) -> SweepPlan:
    """Recommend the step Δd and the number of frames for a lens and a height range.

    Why this step: with a Gaussian PSF of width ``σ(δ)² = σ0² + (g·δ)²`` (``g`` px per mm
    of defocus ``δ``), a texture component of angular frequency ``ω`` keeps the amplitude
    ``exp(−ω²σ²/2)``, so an energy focus measure (Laplacian, SML) falls as
    ``exp(−ω²σ0²)·exp(−ω²g²δ²)``: a Gaussian in z with ``σ_F = 1 / (√2·ω·g)``. This is
    exactly the model the SFF depth step fits with 3-point Gaussian interpolation. That
    fit needs the two neighbours of the peak frame well above the noise: with
    ``Δd = σ_F`` (the default ``frames_per_sigma=1``) the worse neighbour of a peak that
    falls half-way between frames is still at ``exp(−1.5²/2) ≈ 32 %`` of the peak, while
    ``Δd = 2σ_F`` would leave it at 1 %. A smaller step only costs frames.

    Parameters
    ----------
    optics : Optics
    height_range_mm : (lo, hi)
        Lowest and highest surface heights to measure (mm).
    texture_cyc_px : float
        Dominant spatial frequency (cycles/px) the focus measure responds to; 0.2 suits
        band-limited textures seen through a slightly soft lens.
    frames_per_sigma : float
        Frames per σ_F (Δd = σ_F / frames_per_sigma).
    margin_frames : int
        Extra frames below ``lo`` and above ``hi`` so extreme heights peak inside the sweep.

    Returns
    -------
    SweepPlan

    Examples
    --------
    >>> plan = recommend_sweep(Optics(), (0.0, 1.0))
    >>> 0.03 < plan.step_mm < 0.06
    True
    """
    if not isinstance(optics, Optics):
        raise InputError(f"optics must be an Optics; got {type(optics).__name__}")
    try:
        lo, hi = (float(v) for v in height_range_mm)
    except (TypeError, ValueError):
        raise InputError(
            f"height_range_mm must be two numbers (lo, hi); got {height_range_mm!r}"
        ) from None
    if not (math.isfinite(lo) and math.isfinite(hi)) or hi < lo:
        raise InputError(f"height_range_mm must be finite with lo <= hi; got ({lo}, {hi})")
    f_tex = _positive(texture_cyc_px, "texture_cyc_px")
    if f_tex > 0.5:
        raise InputError(f"texture_cyc_px must be <= 0.5 (Nyquist); got {f_tex}")
    fps = _positive(frames_per_sigma, "frames_per_sigma")
    if not isinstance(margin_frames, (int, np.integer)) or margin_frames < 0:
        raise InputError(f"margin_frames must be an integer >= 0; got {margin_frames!r}")
    g = optics.blur_rate_px_per_mm()
    omega = 2.0 * math.pi * f_tex
    sigma_f = 1.0 / (math.sqrt(2.0) * omega * g)
    step = sigma_f / fps
    n_inner = int(math.ceil((hi - lo) / step - 1e-9)) + 1
    n = n_inner + 2 * int(margin_frames)
    centre = 0.5 * (lo + hi)
    z = centre + (np.arange(n, dtype=np.float64) - (n - 1) / 2.0) * step
    return SweepPlan(
        step_mm=step,
        n_frames=n,
        z_mm=z,
        focus_sigma_mm=sigma_f,
        depth_of_field_mm=optics.depth_of_field_mm(),
    )


def _finite(value: Any, name: str) -> float:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.number)):
        raise InputError(f"{name} must be a number; got {value!r}")
    value = float(value)
    if not math.isfinite(value):
        raise InputError(f"{name} must be finite; got {value}")
    return value


def _positive(value: Any, name: str) -> float:
    value = _finite(value, name)
    if value <= 0:
        raise InputError(f"{name} must be > 0; got {value}")
    return value
