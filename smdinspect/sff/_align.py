"""Frame alignment for ordinary (non-telecentric) lenses.

Magnification changes with focus, and a real stage shifts a little: the focus measures
of different frames must be brought onto one pixel grid before they are compared.

:func:`estimate_alignment` runs before the focus pass, on reduced grey copies: every
frame is registered to its predecessor with OpenCV's ECC (enhanced correlation
coefficient) maximisation under an affine motion, and the pairwise warps are chained
(neighbours look alike in blur, far frames do not). The steps are then replaced by a
thin-lens model of the sweep (:func:`_fit_sweep`: the scale a smooth function of z
fitted to the frames that carry scale information, about one fixed centre), checked
against direct registrations of frames a span apart; if those disagree with the model,
only the steps of mostly blurred frames follow it. The reference grid is then the
**most magnified** frame's: every other frame sees more of the scene, so the field
every frame sees is nearly that whole frame (:attr:`Alignment.field`), and no frame is
stretched past its own resolution.

The focus measure of each frame is computed on the frame's own pixels and only then
resampled onto the reference grid. Resampling an image first would low-pass it by an
amount that depends on the sub-pixel shift (linear interpolation halves the Laplacian
energy at a half-pixel shift), so the unresampled reference frame would look sharpest
and the heights would pile up on it; the focus measure, a window sum, is smooth and
survives resampling.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from dataclasses import field as _field
from typing import Callable

import cv2
import numpy as np

from ._focus import noise_sigma

__all__ = ["Alignment", "estimate_alignment"]

log = logging.getLogger(__name__)

_MAX_SIDE = 640  # ECC runs on an image no larger than this (pixels)
#: A pair whose ECC correlation is below this is a failed registration.
MIN_CORRELATION = 0.3
#: Loop-closure check: the sweep is cut into this many spans, each registered directly,
#: and a disagreement with the chain above CHECK_TOLERANCE_PX (full-size pixels, at the
#: image's corners) marks the alignment inconsistent.
CHECK_SPANS = 4
CHECK_TOLERANCE_PX = 2.0
#: A frame whose scale information (mean squared radial gradient of the contrast-
#: normalised image) is below this fraction of the sweep's best is mostly blur: a direct
#: registration with it neither confirms nor refutes the alignment.
INFO_FRACTION = 0.1
#: ECC runs coarse to fine over up to this many pyramid levels, the coarsest no smaller
#: than _ECC_MIN_SIDE pixels.
_ECC_LEVELS = 3
_ECC_MIN_SIDE = 64
_ECC_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-6)


@dataclass(frozen=True, eq=False)
class Alignment:
    """Where every frame lies on the reference grid.

    Attributes
    ----------
    transforms : list of (3, 3) float64
        For frame n, the map from reference-grid pixel coordinates (x = col, y = row)
        to frame n's pixel coordinates.
    reference : int
        Index of the frame whose grid is the output grid (the most magnified one).
    shape : (H, W)
        Size of the reference grid.
    field : (H, W) bool
        Reference pixels that every frame sees.
    correlation : list of float
        ECC correlation of each frame with its predecessor (1.0 for frame 0).
    failed : list of int
        Frames whose registration failed (ECC did not converge or correlated below
        ``MIN_CORRELATION``) or whose step disagreed with the others' magnification
        change; their step is the median of the good steps.
    inconsistent : list of [i, j]
        Spans of the sweep whose direct registration disagrees with the chain of steps
        (loop closure, :func:`_check_chain`): the alignment is wrong there.
    verified_spans : int
        Spans whose direct registration converged (and so checked the chain).
    checks : int
        Spans that could be checked: 0 for a stack too short to cut into spans, and a
        span with a frame that is all blur (:data:`INFO_FRACTION`) does not count.
    model : dict
        The thin-lens model of the sweep (:func:`_fit_sweep`), for ``summary.json``.
    modelled : tuple of int
        Frames whose step from the frame before follows the model.
    noise_sigma : float
        Sensor noise σ in the frames' grey units: the median of the per-frame estimates
        (:func:`~smdinspect.sff.noise_sigma`). Texture inflates an estimate and
        JPEG smoothing of defocused frames deflates it; too large is the safe side (the
        magnification correction of :func:`reconstruct` then leaves weak texture
        uncorrected instead of faking a peak in textureless pixels). 0 when unknown.
    """

    transforms: list[np.ndarray]
    reference: int
    shape: tuple[int, int]
    field: np.ndarray
    correlation: list[float] = _field(default_factory=list)
    failed: list[int] = _field(default_factory=list)
    inconsistent: list[list[int]] = _field(default_factory=list)
    verified_spans: int = 0
    checks: int = 0
    noise_sigma: float = 0.0
    model: dict = _field(default_factory=dict)
    modelled: tuple[int, ...] = ()

    @property
    def ok(self) -> bool:
        return not self.failed and not self.inconsistent

    @property
    def trusted(self) -> bool:
        """The chain agrees with every direct registration over a span of the sweep and
        at least one of those converged (or no span can be checked and every failed
        step was replaced by the thin-lens model)."""
        if self.inconsistent:
            return False
        return self.verified_spans > 0 or (self.checks == 0
                                           and not set(self.failed) - set(self.modelled))

    def scale(self, n: int) -> float:
        """Linear size of a reference pixel in frame n's pixels (≤ 1 by construction)."""
        return float(np.sqrt(abs(np.linalg.det(self.transforms[n][:2, :2]))))

    def warp(self, image: np.ndarray, n: int, *, interpolation: int = cv2.INTER_LINEAR,
             border_value: float = 0.0, rows: tuple[int, int] | None = None,
             src_row: int = 0) -> np.ndarray:
        """Resample frame n's ``image`` (its own grid) onto the reference grid.

        With ``rows = (lo, hi)`` only those rows of the reference grid are made, from an
        ``image`` that holds frame n's rows from ``src_row`` on (:meth:`source_rows`).
        """
        a = self.transforms[n]
        h, w = self.shape
        if rows is not None:
            lo, hi = rows
            a = (np.array([[1, 0, 0], [0, 1, -src_row], [0, 0, 1]], np.float64) @ a
                 @ np.array([[1, 0, 0], [0, 1, lo], [0, 0, 1]], np.float64))
            h = hi - lo
        if image.shape[:2] == (h, w) and np.allclose(a, np.eye(3), atol=1e-9):
            return image
        return cv2.warpAffine(image, a[:2], (w, h), flags=interpolation | cv2.WARP_INVERSE_MAP,
                              borderMode=cv2.BORDER_CONSTANT, borderValue=border_value)

    def source_rows(self, n: int, rows: tuple[int, int], pad: int) -> tuple[int, int]:
        """Rows ``(first, end)`` of frame n that the reference grid's ``rows = (lo, hi)``
        are resampled from, with ``pad`` rows more each side (for the focus windows)."""
        a = self.transforms[n]
        w = self.shape[1]
        ys = [a[1, 0] * x + a[1, 1] * y + a[1, 2] for x in (0, w - 1) for y in (rows[0], rows[1] - 1)]
        frame_h = self.shape[0]
        return (max(0, int(np.floor(min(ys))) - pad),
                min(frame_h, int(np.ceil(max(ys))) + 1 + pad))

    def summary(self) -> dict:
        """JSON-able description (for ``summary.json``)."""
        return {
            "ok": self.ok,
            "reference_frame": self.reference,
            "failed_frames": list(self.failed),
            "inconsistent_spans": [list(p) for p in self.inconsistent],
            "verified_spans": self.verified_spans,
            "trusted": self.trusted,
            "min_correlation": round(min(self.correlation), 4) if self.correlation else None,
            "scale_range": [round(min(self.scale(n) for n in range(len(self.transforms))), 4),
                            round(max(self.scale(n) for n in range(len(self.transforms))), 4)],
            "field_fraction": round(float(self.field.mean()), 4),
            "magnification_trend": self.magnification_trend(),
            "model": dict(self.model),
            "transforms": [a.tolist() for a in self.transforms],
        }

    def parallax_sources(self, z_mm: np.ndarray, height_mm: np.ndarray, reliable: np.ndarray
                         ) -> tuple[np.ndarray | None, dict]:
        """Where every output pixel's in-focus point was measured (perspective parallax).

        On a rig that moves the camera, a point is sharp when it lies at the working
        distance, so in the frame where it is in focus it is imaged at the focused
        plane's magnification, the one ``pixel_size_mm`` describes, whatever its height.
        The alignment registers each frame by its content onto the most magnified
        frame's grid, and so magnifies the frame focused at ``z`` by ``1 / scale(z)``:
        a raised point lands further from the optical centre ``c`` than a low one at
        the same place (~1 % of the distance to the centre per mm of height at a 100 mm
        working distance). Each reliable pixel at height ``h`` (the median of its 5x5
        neighbourhood, unreliable pixels counting as ``h0``) is moved to
        ``c + (x - c) · scale(h) / scale(h0)``, with ``ln scale`` a least-squares line in
        ``z`` through the frames' scales, ``h0`` the median reliable height (the board,
        on a board: it stays where it is) and ``c`` the image centre (the principal
        point of a lens looking straight down); unreliable pixels stay. Where two land
        on one pixel the higher wins (it hides the other from the lens), a measured one
        over an unreliable one. A one-pixel gap between two landed pixels within a frame
        step of each other is rounding where the shift grows by a pixel: it takes its
        neighbour. What is still empty takes what lands there when every pixel moves,
        an unreliable one with a smooth fill of the measured heights around it
        (:func:`_smooth_fill`): a measured pixel that moved off beside unreliable ones
        leaves no hole (2.5 % of metal-bore's field with ``--step-mm 0.1`` came out
        "hidden" that way); only a place hidden behind a raised part's edge, where
        nothing lands either way, stays empty and unreliable. (Only for the empty
        places: moving the unreliable pixels everywhere gave their guessed positions the
        places the first move fills from measured neighbours, 0.7 % fewer reliable
        pixels on an ordinary-lens board, and more joints unreliable.)
        An output pixel is ``scale(h0)`` times the focused plane's pixel (``pixel_scale``).

        A magnification that grows with z is a rig that focuses with the lens (or z
        runs the wrong way): its parallax depends on the distance to the lens, which
        the frames do not give, so nothing is corrected.

        Returns
        -------
        sources : (H, W) int64 or None
            Flat index of the pixel each output pixel takes; -1 where nothing landed.
        info : dict
            ``corrected``, ``scale_per_mm`` (relative magnification change per mm of z)
            and, when corrected, ``reference_height_mm`` (h0), ``pixel_scale``,
            ``max_shift_px`` and ``hidden_fraction`` (pixels nothing landed on).
        """
        z = np.asarray(z_mm, np.float64)
        n = len(self.transforms)
        if z.size != n or n < 2 or np.ptp(z) <= 0:
            return None, {"corrected": False, "reason": "fewer than two frames in z"}
        g, a = np.polyfit(z, np.log([self.scale(i) for i in range(n)]), 1)
        info: dict = {"corrected": False, "scale_per_mm": round(float(np.expm1(g)), 6)}
        if not g < 0:
            info["reason"] = "magnification grows with z (a rig that focuses with the lens)"
            return None, info
        sel = np.asarray(reliable, bool) & self.field & np.isfinite(height_mm)
        h0 = float(np.median(height_mm[sel])) if sel.any() else float(np.median(z))
        known = np.where(sel, np.clip(height_mm, z.min(), z.max()), h0).astype(np.float32)
        step = float(np.median(np.abs(np.diff(z))))
        # the measured pixels move (unreliable ones counting as h0 in their medians),
        # the unreliable ones stay where they are
        local = cv2.medianBlur(known, 5)
        sources, shift = _land(local, sel, g, h0, stay=~sel)
        _fill_rounding_gaps(sources, local.ravel(), step)
        # what that leaves empty (a measured pixel moved off, no other came) is filled
        # from a move of every pixel, an unreliable one with a smooth fill of the
        # measured heights around it: it travels with the surface it lies on
        hole = sources < 0
        if hole.any():
            fill = _smooth_fill(known, sel, h0)
            local = np.where(sel, cv2.medianBlur(np.where(sel, known, fill), 5), fill)
            every, _ = _land(local, sel, g, h0, stay=None)
            _fill_rounding_gaps(every, local.ravel(), step)
            sources[hole] = every[hole]
        info.update(corrected=True, reference_height_mm=round(h0, 5),
                    pixel_scale=round(float(np.exp(g * h0 + a)), 6),
                    max_shift_px=round(shift, 2),
                    hidden_fraction=round(float(np.mean(sources < 0)), 6))
        return sources, info

    def magnification_trend(self) -> float:
        """Relative magnification change from the first frame to the last (frames in
        ascending z), from a least-squares line through the frames' scales: > 0 when
        the image grows with z. On a rig that moves the camera the image shrinks as the
        camera (and z) goes up, so a clear positive trend there means z runs the wrong
        way; a rig that focuses with the lens magnifies as it focuses nearer (up)."""
        scales = np.array([self.scale(n) for n in range(len(self.transforms))])
        if scales.size < 2:
            return 0.0
        slope, mid = np.polyfit(np.arange(scales.size), scales, 1)
        return round(float(slope * (scales.size - 1) / max(np.mean(scales), 1e-9)), 4)


#: Smoothing (σ, px) of the heights that move the unreliable pixels, and the density of
#: reliable pixels at which they count as much as the reference height (sparse, isolated
#: ones barely move their surroundings) (:meth:`Alignment.parallax_sources`).
FILL_SMOOTH_PX = 10.0
FILL_PRIOR_DENSITY = 0.02


def _smooth_fill(values: np.ndarray, known: np.ndarray, default: float) -> np.ndarray:
    """(H, W) float32: a Gaussian-weighted mean of ``values`` over the ``known`` pixels
    around each pixel, drawn towards ``default`` where they are sparse."""
    m = known.astype(np.float32)
    num = cv2.GaussianBlur(np.where(known, values, 0).astype(np.float32), (0, 0),
                           FILL_SMOOTH_PX)
    den = cv2.GaussianBlur(m, (0, 0), FILL_SMOOTH_PX)
    num += np.float32(FILL_PRIOR_DENSITY * default)
    den += np.float32(FILL_PRIOR_DENSITY)
    return num / den


def _land(local: np.ndarray, measured: np.ndarray, g: float, h0: float, *,
          stay: np.ndarray | None) -> tuple[np.ndarray, float]:
    """Forward parallax move: every pixel (those of ``stay`` excepted: they keep their
    own place) goes to ``c + (x − c)·exp(g·(local − h0))``; where several land on one
    pixel the highest ``measured`` one wins, else the highest. Returns the (H, W) flat
    source index per pixel (−1 where nothing landed) and the largest shift (px)."""
    h, w = local.shape
    index = np.int32 if h * w < 2**31 else np.int64
    movers = np.flatnonzero(np.ones(h * w, bool) if stay is None else ~stay.ravel())
    movers = movers.astype(index, copy=False)
    rows, cols = np.divmod(movers, index(w))
    f = np.exp(g * (local.ravel()[movers] - h0), dtype=np.float32)
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    tx = np.rint(cx + (cols - cx) * f).astype(index)
    ty = np.rint(cy + (rows - cy) * f).astype(index)
    del f
    shift = float(np.hypot(tx - cols, ty - rows).max()) if movers.size else 0.0
    inside = (tx >= 0) & (tx < w) & (ty >= 0) & (ty < h)
    sources = np.full(h * w, -1, np.int64)
    if stay is not None:
        kept = np.flatnonzero(stay)
        sources[kept] = kept
    key, src = ty[inside] * index(w) + tx[inside], movers[inside]
    del tx, ty, inside
    if src.size == 0:   # nothing moved lands inside the image
        return sources.reshape(h, w), shift
    # per target the highest measured pixel wins, else the highest (a guessed height
    # never hides a measured one): a priority of 2^21 height levels over the image's
    # range, plus 2^21 for a measured pixel; the highest priority per target, scattered
    lv = local.ravel()[src]
    lo, span = float(lv.min()), max(float(np.ptp(lv)), 1e-9)
    prio = ((lv - lo) * ((2**21 - 1) / span)).astype(np.int32)
    del lv
    prio += measured.ravel()[src].astype(np.int32) << 21
    best = np.full(h * w, -1, np.int32)
    np.maximum.at(best, key, prio)
    win = prio == best[key]
    sources[key[win]] = src[win]
    return sources.reshape(h, w), shift


def _fill_rounding_gaps(sources: np.ndarray, height: np.ndarray, step: float) -> None:
    """Fill, in place, the one-pixel gaps (``sources`` < 0) of a parallax move between two
    landed pixels whose heights (``height``, flat) differ by at most ``step``: rounding
    where the shift grows by a pixel, not a hidden surface, so the gap takes its left
    (then upper) neighbour. Gaps at a height step stay hidden."""
    for axis in (1, 0):
        line = np.moveaxis(sources, axis, -1)   # a view: writing to ``mid`` fills sources
        before, mid, after = line[..., :-2], line[..., 1:-1], line[..., 2:]
        gap = (mid < 0) & (before >= 0) & (after >= 0)
        take = before[gap]
        near = np.abs(height[take] - height[after[gap]]) <= step
        idx = tuple(i[near] for i in np.nonzero(gap))
        mid[idx] = take[near]


def _small(gray: np.ndarray, scale: float) -> np.ndarray:
    g = gray.astype(np.float32)
    if scale < 1.0:
        h, w = g.shape
        g = cv2.resize(g, (max(8, round(w * scale)), max(8, round(h * scale))),
                       interpolation=cv2.INTER_AREA)
    # normalise contrast so ECC sees comparable images across focus
    return (g - g.mean()) / (g.std() + 1e-6)


def _ecc(a: np.ndarray, b: np.ndarray, warp: np.ndarray):
    """Affine ECC of ``b`` onto ``a`` from ``warp`` (float32 2 × 3): (correlation, warp);
    raises cv2.error when it does not converge."""
    return cv2.findTransformECC(a, b, warp, cv2.MOTION_AFFINE, _ECC_CRITERIA, None, 5)


def _ecc_pyramid(prev: np.ndarray, cur: np.ndarray, init: np.ndarray, n: int):
    """Affine ECC of ``cur`` onto ``prev`` (both :func:`_small`): at full size from
    ``init``, and if that fails, coarse to fine.

    ECC follows image gradients, so it only converges when the start is within about
    half a texture period; fine texture and a magnification change of a few pixels at the
    border defeat it from the identity. Halving the images widens that reach: each level
    starts from the coarser one's warp (translation doubled); a level that fails (noise can
    stop the finer ones) keeps the coarser warp. Returns (correlation, warp) of the finest
    level that converged or of the full-size attempt, whichever correlates better;
    correlation 0 and ``init`` when none converged.
    """
    try:  # at full size first: the texture the coarse levels blur away may be all there is
        cc, warp = _ecc(prev, cur, init.astype(np.float32).copy())
        if cc >= MIN_CORRELATION:
            return float(cc), warp
        single: tuple[float, np.ndarray] = (float(cc), warp)
    except cv2.error:
        single = (0.0, init)
    levels = [(prev, cur)]
    while min(levels[-1][0].shape) >= 2 * _ECC_MIN_SIDE and len(levels) < _ECC_LEVELS:
        a, b = levels[-1]
        levels.append((cv2.pyrDown(a), cv2.pyrDown(b)))
    factor = 2.0 ** (len(levels) - 1)
    warp = init.astype(np.float32).copy()
    warp[:, 2] /= factor
    best: tuple[float, np.ndarray] = (0.0, init)
    for level, (a, b) in enumerate(reversed(levels)):
        try:
            cc, warp = _ecc(a, b, warp)
            full = warp.copy()
            full[:, 2] *= 2.0 ** (len(levels) - 1 - level)
            best = (float(cc), full)  # the finest level that converged
        except cv2.error as exc:
            # keep the coarser level's warp (noise can stop the finer one)
            log.debug("frame %d: ECC failed at level %d: %s", n, len(levels) - 1 - level,
                      str(exc).splitlines()[-1])
        if level < len(levels) - 1:
            warp = warp.copy()
            warp[:, 2] *= 2.0
    return max(single, best, key=lambda r: r[0])


def _direct_spans(kept: dict[int, np.ndarray], to_frame: list[np.ndarray],
                  scale: float) -> list[tuple[int, int, np.ndarray | None]]:
    """Register the kept frames a span apart directly, ECC started from the chain's own
    answer: (i, j, full-size step from frame i to frame j, or None when ECC did not
    converge or correlated below MIN_CORRELATION)."""
    frames = sorted(kept)
    s = np.diag([scale, scale, 1.0])
    out: list[tuple[int, int, np.ndarray | None]] = []
    for i, j in zip(frames, frames[1:]):
        chain = s @ to_frame[j] @ np.linalg.inv(to_frame[i]) @ np.linalg.inv(s)  # small px
        try:
            cc, warp = _ecc(kept[i], kept[j], chain[:2].astype(np.float32))
        except cv2.error:
            cc = 0.0
        if cc < MIN_CORRELATION:
            out.append((i, j, None))
            continue
        full = np.linalg.inv(s) @ np.vstack([warp, [0, 0, 1]]).astype(np.float64) @ s
        out.append((i, j, full))
    return out


def _check_chain(spans: list[tuple[int, int, np.ndarray | None]], to_frame: list[np.ndarray],
                 shape: tuple[int, int], scale_info: list[float], *, quiet: bool = False
                 ) -> tuple[list[list[int]], int, int]:
    """Loop closure: compare each direct registration of frames a span apart
    (:func:`_direct_spans`) with the alignment's own answer. Each chained step may
    converge on noise or on shading that stays with the sensor and still correlate; a
    direct registration over several steps that converges elsewhere shows the alignment
    is wrong. A span with a frame that carries less than INFO_FRACTION of the sweep's
    best scale information (:func:`_content_centre`: all blur) proves nothing either
    way, like one whose ECC did not converge. Returns the [i, j] pairs whose direct and
    chained transforms move a point at the image's edge by more than CHECK_TOLERANCE_PX
    apart, how many pairs were compared, and how many could have been (frames not all
    blur: a sweep whose spans are all blur cannot be checked, which is not a failed
    check)."""
    bad = []
    verified = 0
    checkable = 0
    best = max(scale_info) if scale_info else 0.0
    h, w = shape
    corners = np.array([[0, 0, 1], [w - 1, 0, 1], [0, h - 1, 1], [w - 1, h - 1, 1]], float).T
    for i, j, warp in spans:
        if min(scale_info[i], scale_info[j]) < INFO_FRACTION * best:
            continue
        checkable += 1
        if warp is None:
            continue
        verified += 1
        chain = to_frame[j] @ np.linalg.inv(to_frame[i])
        moved = np.abs(warp[:2] @ corners - chain[:2] @ corners).max()
        if moved > CHECK_TOLERANCE_PX:
            bad.append([i, j])
            if not quiet:
                log.warning("alignment: frames %d and %d registered directly disagree with "
                            "the chain of steps between them by %.1f px at the image edge",
                            i, j, moved)
    return bad, verified, checkable


def _replace_outlier_steps(steps: list[np.ndarray], failed: list[int],
                           z_mm: np.ndarray | None) -> dict[int, str]:
    """Failed steps, and steps whose magnification change disagrees with the others,
    become the median of the good steps (in place; ``failed`` gains the outliers).
    Returns a message for each outlier step (by frame; the caller decides whether it
    matters: a step the thin-lens model replaces anyway does not).

    A lens's magnification changes smoothly with focus, by about the same factor per
    unit of z; ECC on a frame that is mostly blur and noise can converge to a wrong
    scale with a passable correlation, and each wrong step shifts every later frame.
    The per-step log-scale, per mm of z when ``z_mm`` is given, is an outlier when it is
    more than 6 MADs (and 0.2 %) from the median of the converged steps.
    """
    n = len(steps)
    notes: dict[int, str] = {}
    if n < 4:
        return notes
    dz = np.abs(np.diff(np.asarray(z_mm, float))) if z_mm is not None else np.ones(n - 1)
    dz = np.where(dz > 0, dz, np.median(dz[dz > 0]) if np.any(dz > 0) else 1.0)
    rate = np.array([_log_scale(a) for a in steps[1:]]) / dz
    good = np.array([i not in failed for i in range(1, n)])
    if good.sum() < 3:
        return notes
    med = float(np.median(rate[good]))
    mad = 1.4826 * float(np.median(np.abs(rate[good] - med)))
    tol = max(6 * mad, 0.002 / float(np.median(dz)))
    bad = ~good | (np.abs(rate - med) > tol)
    keep = [steps[i + 1] for i in np.nonzero(~bad)[0]]
    if not keep:
        return notes
    typical = np.median(np.stack(keep), axis=0)
    for i in np.nonzero(bad)[0]:
        scale = float(np.exp(med * (dz[i] - np.median(dz))))  # a longer step, more change
        step = typical.copy()
        step[:2, :2] *= scale
        steps[i + 1] = step
        i = int(i)
        if i + 1 not in failed:
            notes[i + 1] = (f"frame {i + 1}: alignment step to frame {i} disagrees with the "
                            f"others' magnification change ({100 * rate[i]:.2f} % against "
                            f"{100 * med:.2f} % per mm); replaced by their median")
            failed.append(i + 1)
    failed.sort()
    return notes


def _content_centre(small: np.ndarray) -> tuple[np.ndarray, float]:
    """Where ECC measures a step, and how well the frame fixes a scale.

    Returns the centroid of the image's squared gradient (``small`` pixel coordinates,
    x then y: ECC follows gradients, so an affine step that gets the scale slightly wrong
    is still right there) and the mean squared radial gradient
    ``((∇I · (x − centre)) / width)²`` of the contrast-normalised image: the information a
    frame carries about a scale about its centre (a defocused frame, all blur, carries
    little, however well it correlates with its neighbour)."""
    gx = cv2.Sobel(small, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(small, cv2.CV_32F, 0, 1, ksize=3)
    e = gx * gx + gy * gy
    total = float(e.sum())
    h, w = small.shape
    xs = np.arange(w, dtype=np.float32) - (w - 1) / 2.0
    ys = np.arange(h, dtype=np.float32) - (h - 1) / 2.0
    info = float(np.mean((gx * xs[None, :] + gy * ys[:, None]) ** 2)) / (w * w)
    if not total > 0:
        return np.array([(w - 1) / 2.0, (h - 1) / 2.0]), 0.0
    return np.array([float((e.sum(axis=0) * np.arange(w)).sum()) / total,
                     float((e.sum(axis=1) * np.arange(h)).sum()) / total]), info


def _robust_weights(resid: np.ndarray, base: np.ndarray, floor: float) -> np.ndarray:
    """Tukey biweight of ``resid`` (scale: 4.685 × max(MAD σ, ``floor``)) times ``base``."""
    used = resid[base > 0]
    sigma = 1.4826 * float(np.median(np.abs(used - np.median(used)))) if used.size else 0.0
    u = resid / (4.685 * max(sigma, floor))
    return base * np.where(np.abs(u) < 1, (1 - u * u) ** 2, 0.0)


@dataclass(frozen=True, eq=False)
class _Sweep:
    """The thin-lens model of a sweep (:func:`_fit_sweep`), per step n-1 -> n."""

    scale: np.ndarray     # (n-1,) the model's scale of each step
    centre: np.ndarray    # (2,) the centre of expansion, full-size pixels
    shift: np.ndarray     # (n-1, 2) each step's sideways shift
    blurred: np.ndarray   # (n-1,) bool: a frame of the step carries no scale information
    info: dict            # for summary.json

    def steps(self, measured: list[np.ndarray], *, every_step: bool
              ) -> tuple[list[np.ndarray], set[int]]:
        """The steps with the model's in place of the measured ones: every step, or
        (``every_step`` False: a rig that also turns or shears a little keeps what ECC
        measured on the frames that show it) only the blurred ones. Returns the steps and
        the frames whose step (from the frame before) follows the model."""
        use = np.ones_like(self.blurred) if every_step else self.blurred
        out = list(measured)
        for k in np.nonzero(use)[0] + 1:
            step = np.eye(3)
            step[:2, :2] *= self.scale[k - 1]
            step[:2, 2] = (1 - self.scale[k - 1]) * self.centre + self.shift[k - 1]
            out[k] = step
        return out, {int(k) for k in np.nonzero(use)[0] + 1}


def _log_scale(a: np.ndarray) -> float:
    """ln of the linear scale of an affine map (its 2 x 2 part's determinant, rooted)."""
    return 0.5 * float(np.log(abs(np.linalg.det(a[:2, :2]))))


def _fit_sweep(steps: list[np.ndarray], failed: list[int], z_mm: np.ndarray | None,
               centres: list[np.ndarray], scale_info: list[float], shape: tuple[int, int],
               spans: list[tuple[int, int, np.ndarray | None]]) -> _Sweep | None:
    """A physical model of the sweep from the measured steps (None: too few to fit).

    Moving a camera or a focusing lens along its axis scales the image about the optical
    centre ``c`` by a factor that is a smooth function of z; a real stage adds a small
    sideways shift at each step. Chaining per-step ECC estimates instead lets each
    frame's small error accumulate into pixels at the image edge, above all on frames
    that are mostly blur (where only a raised part is sharp, ECC's scale is noise and
    bias however well the frames correlate). So:

    * each frame's scale information is the mean squared radial gradient of its
      contrast-normalised image (:func:`_content_centre`); a step (or a direct
      registration a span apart, ``spans``) weighs the smaller of its two frames', and
      only those above INFO_FRACTION of the best shape the fit;
    * the scale follows the thin lens (:func:`_fit_thin_lens`) fitted to their ln scale;
    * ``c`` is the weighted least-squares fixed point of those steps and spans
      (``(I − A) c = b``), pulled slightly towards the image centre;
    * each step's sideways shift is where the measured step moves the point it was
      measured best at (its template frame's gradient centroid) minus where the pure
      scale about ``c`` moves it; shifts that stand out from the others (Tukey weights)
      become their weighted median.
    """
    n = len(steps)
    if n < 4:
        return None
    z = np.arange(n, dtype=np.float64) if z_mm is None else np.asarray(z_mm, np.float64)
    dz = np.diff(z)
    if not np.all(dz != 0):
        return None
    # a step weighs what the blurrier of its two frames tells about a scale
    base = np.array([0.0 if k in failed else min(scale_info[k - 1], scale_info[k])
                     for k in range(1, n)])
    if np.count_nonzero(base) < 3:
        return None
    zc = float(np.average(0.5 * (z[1:] + z[:-1]), weights=base))
    # the measured changes of scale: every step, and the direct registrations a span
    # apart (a longer lever on the scale and on the centre)
    pairs = [(k - 1, k, steps[k], base[k - 1]) for k in range(1, n)]
    pairs += [(i, j, warp, min(scale_info[i], scale_info[j])) for i, j, warp in spans
              if warp is not None]
    i0, i1, maps, wts = (list(x) for x in zip(*pairs))
    wts = np.array(wts)
    # only frames that carry scale information (not all blur) shape the curve and c
    informative = wts >= INFO_FRACTION * float(np.max(wts))
    fit_wts = np.where(informative, wts, 0.0) if np.count_nonzero(informative) >= 3 else wts
    half = float(max(np.max(np.abs(z - zc)), 1e-9))
    a, b = _fit_thin_lens(np.array([_log_scale(m) for m in maps]), (z[i0] - zc) / half,
                          (z[i1] - zc) / half, fit_wts, floor=1e-4)
    t = (z - zc) / half
    log_s = np.diff(np.log1p(b * t) - np.log1p(a * t))
    s = np.exp(log_s)
    # the fixed point of the informative steps and spans; with no magnification change
    # at all (e.g. identical frames) the image centre
    h, w_img = shape
    centre = np.array([(w_img - 1) / 2.0, (h - 1) / 2.0])
    lhs = np.zeros((2, 2))
    rhs = np.zeros(2)
    for wt, m in zip(wts[informative], [m for m, k in zip(maps, informative) if k]):
        ia = np.eye(2) - m[:2, :2]
        lhs += wt * ia.T @ ia
        rhs += wt * ia.T @ m[:2, 2]
    ridge = 1e-3 * float(np.sum(base)) * max(float(np.median(np.abs(log_s))), 1e-6) ** 2
    c = np.linalg.solve(lhs + ridge * np.eye(2), rhs + ridge * centre)
    # each step's sideways shift at the point it was measured best (ECC's template is
    # frame k - 1)
    shift = np.array([steps[k][:2, :2] @ centres[k - 1] + steps[k][:2, 2]
                      - (c + s[k - 1] * (centres[k - 1] - c)) for k in range(1, n)])
    mag = np.hypot(*(shift - np.median(shift[base > 0], axis=0)).T)
    ws = _robust_weights(mag, base, floor=0.25)
    if ws.sum() > 0:
        shift[ws <= 0] = [np.quantile(shift[:, i], 0.5, weights=ws, method="inverted_cdf")
                          for i in (0, 1)]
    else:
        shift[ws <= 0] = 0.0
    info = {"model": "thin lens: scale (1 + b t) / (1 + a t), t = (z - z0) / half",
            "a": round(a, 6), "b": round(b, 6), "z0_mm": round(zc, 6),
            "half_mm": round(half, 6),
            "centre_px": [round(float(c[0]), 2), round(float(c[1]), 2)],
            "shift_outliers": int(np.count_nonzero((ws <= 0) & (base > 0)))}
    return _Sweep(scale=s, centre=c, shift=shift,
                  blurred=base < INFO_FRACTION * float(np.max(base)), info=info)


def _fit_thin_lens(obs: np.ndarray, t0: np.ndarray, t1: np.ndarray, base: np.ndarray,
                   floor: float) -> tuple[float, float]:
    """Robust fit of the frames' scale as a thin lens makes it, to measured changes
    ``obs[k] = ln scale(t1[k]) − ln scale(t0[k])`` weighted by ``base`` (t: z scaled to
    [-1, 1] over the sweep).

    Magnification is ``v / u``. A camera moving along its axis changes ``u`` linearly in
    z: ``scale ∝ 1 / (1 + a·t)``. A rig that moves the lens or the sensor changes ``v``
    linearly (and ``u`` much less, relative to its size): ``scale ∝ 1 + b·t``. Both are
    fitted (Gauss-Newton under Tukey weights, ``|a|, |b| <= 0.9``: distances stay
    positive over the sweep) and the one with the smaller weighted residual is kept.
    Returns ``(a, b)``, one of them 0."""
    best: tuple[float, float, float] | None = None
    for which in ("a", "b"):
        sign = -1.0 if which == "a" else 1.0
        w = base.copy()
        p = 0.0
        for it in range(30):
            r = obs - sign * (np.log1p(p * t1) - np.log1p(p * t0))
            if it >= 3:   # plain least squares first: Tukey needs a start near the answer
                w = _robust_weights(r, base, floor)
            jac = sign * (t1 / (1 + p * t1) - t0 / (1 + p * t0))
            den = float(np.sum(w * jac * jac))
            if not den > 0:
                break
            p_new = float(np.clip(p + np.sum(w * jac * r) / den, -0.9, 0.9))
            done = abs(p_new - p) < 1e-10 and it >= 3
            p = p_new
            if done:
                break
        r = obs - sign * (np.log1p(p * t1) - np.log1p(p * t0))
        cost = float(np.sum(w * r * r) / max(np.sum(w), 1e-30))
        if best is None or cost < best[0]:
            best = (cost, p if which == "a" else 0.0, p if which == "b" else 0.0)
    return best[1], best[2]


def estimate_alignment(read_gray: Callable[[int], np.ndarray], n_frames: int, *,
                       z_mm: np.ndarray | None = None,
                       progress: Callable[[int, int], None] | None = None) -> Alignment:
    """Register every frame to its neighbour and choose the reference grid.

    Parameters
    ----------
    read_gray : callable(index) -> (H, W) array
        Returns frame ``index``'s grey image at full size.
    n_frames : int
    z_mm : array, optional
        The frames' z (for the outlier test of the steps' magnification change).

    Returns
    -------
    Alignment
    """
    steps = [np.eye(3)]  # frame n-1 coords -> frame n coords, full resolution
    correlation = [1.0]
    failed: list[int] = []
    sigmas: list[float] = []
    prev = None
    last = np.eye(3, dtype=np.float32)[:2]
    shape = None
    # frames kept (small) for the loop-closure check of the chain
    span = max(2, n_frames // CHECK_SPANS)
    check_frames = set(range(0, n_frames, span)) if n_frames >= 2 * span else set()
    kept: dict[int, np.ndarray] = {}
    centres: list[np.ndarray] = []
    scale_info: list[float] = []
    notes: dict[int, str] = {}   # frame -> what went wrong with its step
    for n in range(n_frames):
        gray = read_gray(n)
        if shape is None:
            shape = gray.shape[:2]
            scale = min(1.0, _MAX_SIDE / max(shape))
        sigmas.append(noise_sigma(gray))
        small = _small(gray, scale)
        if n in check_frames:
            kept[n] = small
        centre, info = _content_centre(small)
        centres.append(centre / scale)
        scale_info.append(info)
        if prev is not None:
            cc, warp = _ecc_pyramid(prev, small, last, n)
            if cc < MIN_CORRELATION:
                failed.append(n)
                notes[n] = (f"frame {n}: alignment to frame {n - 1} failed (correlation "
                            f"{cc:.2f}); using the other steps' median")
                warp = last
            last = warp
            correlation.append(float(cc))
            s = np.diag([scale, scale, 1.0])
            steps.append(np.linalg.inv(s) @ np.vstack([warp, [0, 0, 1]]).astype(np.float64) @ s)
        prev = small
        if progress is not None:
            progress(n + 1, n_frames)
    notes.update(_replace_outlier_steps(steps, failed, z_mm))
    spans = _direct_spans(kept, _chain(steps), scale)
    sweep = _fit_sweep(steps, failed, z_mm, centres, scale_info, shape, spans)
    model: dict = {"model": "measured steps"}
    modelled: set[int] = set()
    if sweep is None:
        to_frame = _chain(steps)
        inconsistent, verified, checks = _check_chain(spans, to_frame, shape, scale_info)
    else:
        # every step follows the lens, unless the frames that show it best disagree with
        # a pure scale: then only the blurred ones
        for every_step in (True, False):
            used, modelled = sweep.steps(steps, every_step=every_step)
            to_frame = _chain(used)
            inconsistent, verified, checks = _check_chain(spans, to_frame, shape, scale_info,
                                                          quiet=every_step)
            model = {**sweep.info, "modelled_steps": len(modelled)}
            if not inconsistent:
                break
    for n, note in sorted(notes.items()):
        # a step the thin-lens model replaced is not used: nothing for the user to check
        log.log(logging.DEBUG if n in modelled else logging.WARNING, note)
    ref = int(np.argmax([_log_scale(a) for a in to_frame]))  # where a frame-0 pixel is largest
    inv_ref = np.linalg.inv(to_frame[ref])
    transforms = [a @ inv_ref for a in to_frame]
    return Alignment(transforms=transforms, reference=ref, shape=shape,
                     field=_field(transforms, shape), correlation=correlation, failed=failed,
                     inconsistent=inconsistent, verified_spans=verified,
                     checks=checks, modelled=tuple(sorted(modelled)),
                     noise_sigma=float(np.median(sigmas)) if sigmas else 0.0, model=model)


def _chain(steps: list[np.ndarray]) -> list[np.ndarray]:
    """Frame 0 coordinates -> frame n coordinates, from the steps n-1 -> n."""
    to_frame = [steps[0]]
    for st in steps[1:]:
        to_frame.append(st @ to_frame[-1])
    return to_frame


def _field(transforms: list[np.ndarray], shape: tuple[int, int]) -> np.ndarray:
    """(H, W) bool: reference pixels that land inside every frame (one row at a time
    would be a loop; a frame's footprint is a convex quadrilateral, drawn with OpenCV)."""
    h, w = shape
    ok = np.ones(shape, np.uint8)
    corners = np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], np.float64)
    for a in transforms:
        # frame n's corners in reference coordinates
        inv = np.linalg.inv(a)
        pts = corners @ inv[:2, :2].T + inv[:2, 2]
        poly = np.zeros(shape, np.uint8)
        cv2.fillConvexPoly(poly, np.round(pts * 16).astype(np.int32), 1, lineType=cv2.LINE_8,
                           shift=4)
        ok &= poly
    # stay half a pixel inside the footprints (no interpolation against the border)
    ok = cv2.erode(ok, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=0)
    return ok.astype(bool)
