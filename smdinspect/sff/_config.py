"""Configuration of the shape-from-focus reconstruction."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from enum import Enum

from ..errors import InputError

__all__ = ["FitMethod", "FocusConfig"]


class FitMethod(str, Enum):
    """How the focus curve around its peak is modelled."""

    #: Weighted least squares of the power-law peak F = b + A/(1 + (z − z̄)²/γ²)^p over
    #: ±``fit_half_width`` frames (p from the operator, 2 for squared ones): the shape a
    #: defocus-blurred natural texture gives. The default.
    POWER = "power"
    #: Nayar's 3-point Gaussian interpolation through the peak and its two neighbours.
    GAUSS3 = "gauss3"
    #: Weighted least-squares Gaussian (parabola in log F) over ±``fit_half_width`` frames.
    LSQ = "lsq"
    #: The frame of maximum focus only (no interpolation); for comparison.
    ARGMAX = "argmax"


@dataclass(frozen=True)
class FocusConfig:
    """Settings of :func:`smdinspect.sff.reconstruct`.

    Parameters
    ----------
    operator : str
        Focus measure (see ``smdinspect.sff.OPERATORS``); ``"sml"`` (Nayar's sum of
        modified Laplacian) by default.
    window_px : int
        Odd side of the window U the focus measure is summed over.
    threshold : float
        Nayar's threshold: per-pixel responses below it count as 0 before the window
        sum. Only for operators that sum a response (``FocusOperator(op).uses_threshold``).
    fit : FitMethod or str
        ``"power"`` (default), ``"gauss3"``, ``"lsq"`` or ``"argmax"``; every fit is made
        on F − b, b the curve's floor (its lowest value over the stack).
    fit_half_width : int
        k: the focus curve is kept over ±k frames around its peak; the reliability R and
        the ``lsq`` fit use these 2k+1 samples. Memory holds 2k+1 focus frames at most.
    min_confidence : float
        Pixels with confidence below this are unreliable (default 0.5; see
        :func:`smdinspect.sff.confidence_map`).
    edge_jump_steps : float
        Pixels within half a window of a height step of more than this many frame steps
        (within 5 × 5 reliable pixels) are unreliable: a window straddling a step takes
        the sharper, higher side's height. 0 turns the check off. Default 3.
    halo_ratio : float
        A pixel whose focus peak is this many times weaker than that of a neighbour
        (within a window and 2 px) peaking at least two frames away is unreliable: its peak is
        the defocused neighbour's blur (a halo). 0 turns the check off. Default 4.
    blur_order_ratio : float
        A peak must be the sharpest picture of its neighbourhood: where the peak frame is
        explained as a blur of the frame before or after it this many times better than
        the reverse (residual energies over a ``window_px + 6`` square, on frames reduced
        by 2), the peak is unreliable (a defocused structure's blur or compression
        texture, not a surface; see :mod:`smdinspect.sff._blur_order`). Judged only where
        the stack's blur per frame is at least 1 px (finer steps say nothing about the
        order). 0 turns the check off. Default 2.
    support_steps : float
        A reliable height needs corroboration: one of the pixels a window away (an
        independent window, 16 directions) reliable and within this many frame steps
        (see :func:`smdinspect.sff.unsupported_mask`); isolated peaks made by noise or a
        glint become unreliable. 0 turns the check off. Default 1.5.
    coarse_factor : int
        A second, coarser focus level: each frame's focus averaged over
        ``coarse_factor``² blocks and a 5 × 5 box on that grid (a window about
        ``window_px + 5·coarse_factor`` px wide), tracked on the reduced grid. Where the
        fine level is unreliable for want of texture, a reliable coarse height is used
        (smoother, lower lateral resolution; never where the fine level found a halo).
        0 or 1 turns it off. Default 4.
    coarse_levels : int
        Coarse levels of factors ``coarse_factor``, ``coarse_factor``², …: each fills
        what the finer ones left unreliable (a level needs 8 blocks on the frame's
        shorter side). From the second level on, a pixel is filled only where the finer
        map measured at least half of the level's footprint, consistently, and agrees
        with the reading (``_footprint_agrees`` in ``_reconstruct.py``). Default 2.
    prefilter_px : float or "auto"
        σ (px) of a Gaussian applied to each grey frame before the focus operator, to keep
        a derivative operator off the frequencies where the sensor noise outweighs the
        texture. ``"auto"`` measures the sweep's noise-only bands and picks σ
        (0 when there are none; see :func:`smdinspect.sff.prefilter_sigma`; the
        default); 0 turns it off. With ``align`` σ is in the reference frame's pixels.
        Its heights are judged by the precision cue (the even/odd split of each curve,
        :func:`smdinspect.sff.precision_steps`), which sees the noise a pre-filtered
        footprint still leaves. Measured (benchmarks/accuracy.py,
        benchmarks/real_stacks.py): 48 noise-dominated randomised tuning cases 0.7 % →
        10.0 % coverage with 96.4 → 99.05 % of the reliable heights within 1 Δd (test
        seeds: 0.8 → 7.6 %, 99.97 → 98.90 %); noisy cone 0.24 → 0.11 Δd; metal-bore
        36 → 44 % coverage.
    centroid_correction : bool
        A window on a slope measures the height under its focus energy's centroid, not
        under its centre: move each fine-level height by the local slope times the
        centroid's offset (operators that sum a per-pixel response only; see
        :func:`smdinspect.sff.centroid_correction`). Default on.
    edge_gap_check : bool
        The depth-edge check also looks across a gap of unreliable pixels at a step:
        squares of ``window_px + 2`` px and of ``2·(r + 1) + 1`` px, r the farthest the
        halo test drops weak texture from a strong edge (``window_px + 2`` plus its
        pooling, :func:`~smdinspect.sff._confidence.halo_reach_px`: 27 px for a 9-px
        window), for a rise of the same slope (``edge_jump_steps`` per 5 px); and,
        beside a tall step, where the halo test's reach grows with the depth gap, a
        square of 53 px over the pixels bordering a gap only, for that slope over half
        the square (see :func:`smdinspect.sff.depth_edge_mask`, ``gap_span_px``).
        And where a step's low side is all unreliable, the majority of those
        unreliable pixels' own (textured) peaks, in a ``window_px + 4`` square, reading
        more than a step below (:func:`~smdinspect.sff._confidence.hidden_step_mask`).
        Default on.
    precision_check : bool
        Judge each height's random error (the precision cue: the even/odd split of its
        focus curve, :func:`smdinspect.sff.precision_steps`): unreliable where its 1σ
        exceeds about 0.3 Δd. The precision is reported either way
        (``Surface.precision_mm``, ``precision_mm.tiff``). Default on; off for
        inspection, which fits each joint over many pixels and propagates their noise.
    fit_power : "auto", float or None
        Exponent p of the ``power`` fit's model for the heights. The shape of the focus
        curve is the sweep's (texture spectrum and blur): a broadband texture follows the
        operator's power law, a narrow-band one is close to a Gaussian (large p), and at a
        coarse step a wrong shape terraces the heights. ``"auto"`` picks p from the sweep:
        the candidate under which a central crop's smooth slopes do not vary with the
        fractional frame position (:func:`smdinspect.sff._depth.select_curve_power`;
        ``summary.json`` → ``curve_power``); a number fixes it; None keeps the
        operator's (:attr:`FocusOperator.curve_power`). The confidence cues always use
        the operator's. Measured (benchmarks/accuracy.py): terraces at 2.5 depths of
        field per step 0.070 → 0.026 Δd p-p, demo/dense boards median |error| 0.054 /
        0.060 → 0.038 / 0.041 step. Default "auto".
    own_window_px : int
        Side of a small window centred on each pixel whose focus is tracked beside the
        main one (operators that sum a per-pixel response only). A window on weak
        texture next to a sharp edge, a body's rim or a termination's top, peaks where
        that edge is in focus and reads the edge's height: the band of pixels within half
        a window of the edge takes it. The small window sees the pixel's own texture; a
        height is made unreliable when the small window's focus there is clearly peaked
        (its noise test passes) but its focus at the main peak's frame is below
        :data:`~smdinspect.sff._confidence.OWN_SHARE_MIN` of its peak over the floor: the
        height was borrowed from a neighbour. Such pixels are not filled from the coarse
        level either. 0 turns the check off, and so does a value not below
        ``window_px``; default 5.
    plane_px : int
        Each reliable height becomes the least-squares plane through the reliable
        heights of the ``plane_px`` square around it, at its centre, where at least
        60 % of the square is reliable (:func:`smdinspect.sff.local_plane`): the peaks'
        random error averaged after the peak, with no bias on a slope (a larger focus
        window would mix the depths before it). Odd; 0 or 1 turns it off. Default 5.
        Measured (benchmarks/accuracy.py, tuning seeds 100 and 200): noisy cone
        0.114 / 0.111 → 0.099 / 0.096 Δd, clean cone 0.040 / 0.039 → 0.039 / 0.038;
        48 randomised tuning cases (seeds 300-419) 98.75 → 98.87 % within 1 Δd.
    align : bool
        Register the frames (affine, by ECC) onto the most magnified frame's grid and
        resample their focus measures there; needed for ordinary (non-telecentric)
        lenses (see :func:`smdinspect.sff.estimate_alignment`).
    band_mpixels : float
        Frames larger than this many megapixels are measured in bands of rows, each at
        most this size with its margins, one band after the other (the frames are
        decoded once a band): memory follows the band, not the frame. 0 measures the
        whole frame at once. Default 3.5 (a 2048 x 1536 frame is measured whole).
    workers : int
        Threads that decode frames and compute focus measures (≥ 1).
    """

    operator: str = "sml"
    window_px: int = 9
    threshold: float = 0.0
    fit: FitMethod = FitMethod.POWER
    fit_half_width: int = 3
    fit_power: float | str | None = "auto"
    min_confidence: float = 0.5
    edge_jump_steps: float = 3.0
    halo_ratio: float = 4.0
    blur_order_ratio: float = 2.0
    support_steps: float = 1.5
    coarse_factor: int = 4
    coarse_levels: int = 2
    prefilter_px: float | str = "auto"
    centroid_correction: bool = True
    own_window_px: int = 5
    edge_gap_check: bool = True
    precision_check: bool = True
    plane_px: int = 5
    align: bool = False
    band_mpixels: float = 3.5
    workers: int = 2

    def __post_init__(self) -> None:
        try:
            object.__setattr__(self, "fit", FitMethod(self.fit))
        except ValueError:
            choices = ", ".join(m.value for m in FitMethod)
            raise InputError(f"fit must be one of {choices}; got {self.fit!r}") from None
        from ._focus import OPERATORS

        if self.operator not in OPERATORS:
            raise InputError(
                f"unknown focus operator {self.operator!r}; choose one of {', '.join(OPERATORS)}"
            )
        if not isinstance(self.window_px, int) or self.window_px < 1 or self.window_px % 2 == 0:
            raise InputError(f"window_px must be an odd integer >= 1; got {self.window_px!r}")
        if not (isinstance(self.threshold, (int, float)) and math.isfinite(self.threshold)
                and self.threshold >= 0):
            raise InputError(f"threshold must be a finite number >= 0; got {self.threshold!r}")
        from ._focus import FocusOperator

        if self.threshold > 0 and not FocusOperator(self.operator).uses_threshold:
            raise InputError(f"operator {self.operator!r} takes no threshold; got {self.threshold}")
        if not isinstance(self.fit_half_width, int) or not 1 <= self.fit_half_width <= 10:
            raise InputError(f"fit_half_width must be an integer in 1..10; got {self.fit_half_width!r}")
        if not (0.0 <= self.min_confidence <= 1.0):
            raise InputError(f"min_confidence must be in [0, 1]; got {self.min_confidence!r}")
        if not (isinstance(self.edge_jump_steps, (int, float)) and self.edge_jump_steps >= 0):
            raise InputError(f"edge_jump_steps must be >= 0; got {self.edge_jump_steps!r}")
        if not (isinstance(self.halo_ratio, (int, float)) and math.isfinite(self.halo_ratio)
                and (self.halo_ratio == 0 or self.halo_ratio >= 1)):
            raise InputError(f"halo_ratio must be 0 (off) or >= 1; got {self.halo_ratio!r}")
        if not (isinstance(self.blur_order_ratio, (int, float))
                and not isinstance(self.blur_order_ratio, bool)
                and math.isfinite(self.blur_order_ratio)
                and (self.blur_order_ratio == 0 or self.blur_order_ratio >= 1)):
            raise InputError(f"blur_order_ratio must be 0 (off) or >= 1; "
                             f"got {self.blur_order_ratio!r}")
        if not (isinstance(self.support_steps, (int, float)) and math.isfinite(self.support_steps)
                and self.support_steps >= 0):
            raise InputError(f"support_steps must be >= 0 (0: off); got {self.support_steps!r}")
        if not isinstance(self.coarse_factor, int) or not 0 <= self.coarse_factor <= 16:
            raise InputError(f"coarse_factor must be an integer in 0..16; got {self.coarse_factor!r}")
        if not (self.fit_power is None or self.fit_power == "auto" or (
                isinstance(self.fit_power, (int, float)) and not isinstance(self.fit_power, bool)
                and math.isfinite(self.fit_power) and 0.25 <= self.fit_power <= 16)):
            raise InputError(f'fit_power must be "auto", None or a number in 0.25..16; '
                             f'got {self.fit_power!r}')
        if not isinstance(self.edge_gap_check, bool):
            raise InputError(f"edge_gap_check must be true or false; got {self.edge_gap_check!r}")
        if not isinstance(self.precision_check, bool):
            raise InputError(f"precision_check must be true or false; got {self.precision_check!r}")
        if not isinstance(self.own_window_px, int) or self.own_window_px < 0 or (
                self.own_window_px and self.own_window_px % 2 == 0):
            raise InputError(f"own_window_px must be 0 (off) or an odd integer; "
                             f"got {self.own_window_px!r}")
        if not isinstance(self.plane_px, int) or isinstance(self.plane_px, bool) or (
                self.plane_px < 0 or (self.plane_px > 1 and self.plane_px % 2 == 0)):
            raise InputError(f"plane_px must be 0 or 1 (off) or an odd integer >= 3; "
                             f"got {self.plane_px!r}")
        if not isinstance(self.coarse_levels, int) or not 1 <= self.coarse_levels <= 3:
            raise InputError(f"coarse_levels must be an integer in 1..3; got {self.coarse_levels!r}")
        if not (self.prefilter_px == "auto" or (
                isinstance(self.prefilter_px, (int, float)) and not isinstance(self.prefilter_px, bool)
                and math.isfinite(self.prefilter_px) and 0 <= self.prefilter_px <= 16)):
            raise InputError(f'prefilter_px must be "auto" or a number of pixels in 0..16; '
                             f'got {self.prefilter_px!r}')
        if not isinstance(self.centroid_correction, bool):
            raise InputError(f"centroid_correction must be true or false; got {self.centroid_correction!r}")
        if not (isinstance(self.band_mpixels, (int, float)) and not isinstance(self.band_mpixels, bool)
                and math.isfinite(self.band_mpixels)
                and (self.band_mpixels == 0 or self.band_mpixels >= 0.25)):
            raise InputError(f"band_mpixels must be 0 (whole frames) or at least 0.25; "
                             f"got {self.band_mpixels!r}")
        if not isinstance(self.workers, int) or self.workers < 1:
            raise InputError(f"workers must be an integer >= 1; got {self.workers!r}")

    def to_dict(self) -> dict:
        d = asdict(self)
        d["fit"] = self.fit.value
        return d
