"""Per-joint and per-component measurements on the levelled height map.

Everything here works on the measured surface after the board was located: heights
are above the board plane, corrected per component by the local board level (median of
the bare-board pixels around it); every pad, body and lead outline is mapped into the
image through the registration's placement; numbers come from reliable pixels only.

Pixels within ``body_margin_mm`` of a body (or a gull-wing lead's knee) are never used
for solder: shape from focus spreads a tall edge over about half the focus window, so
those pixels read the body's height, often with full confidence.

Chip end joint
    The *fillet region* is the pad in front of the body's end face, from
    ``body_margin_mm`` out to the pad's outer edge (length L). A concave meniscus that
    wets the termination up to height F and the pad up to its edge is fitted to it:
    ``h(d) = F·(1 − d/L)²`` (d: distance from the end face), robust least squares with
    3-MAD trimming. The joint's max height is F, the fillet height at the termination,
    which is what IPC-A-610 bounds (``fillet_model="meniscus"``; with
    ``"percentile"``, or when the fit has too few pixels, it is the
    ``height_percentile`` percentile of the whole solder area instead; also when the
    fit says the joint is above its band but fits badly — relative RMS residual > 10 %,
    a bulging, convex fillet — since the concave model then overshoots). Also measured:
    the end cap's top (solder climbing over the termination means excess).
Gull-wing heel joint
    The lead's foot hides most of the pad, and the heel fillet hides under the lead's
    bend. Measured: the foot (the flat part of the lead, from the heel to a pixel short
    of the toe) as the ``height_percentile`` percentile (``foot``) and its toe half as
    the median (``lead_mm``: the lead's own height); the *side region*: the pad beside
    the foot and beyond the toe (minus the lead grown by one pixel; the knee rises to
    the mould's exit and its blur would read as solder). The solder on the foot is
    fitted as a meniscus thinning from the heel along the foot onto the lead's top,
    ``z = lead + A·(1 − x/ℓ)²`` (x from the heel, reach ℓ searched, a redescending
    clipped least-squares fit over all the foot's reliable pixels, see
    :func:`_heel_fillet`): ``lead + A`` is the heel fillet's top. Fitted over hundreds of
    pixels it varies between re-placed sweeps 40 % less than the percentile, which
    rests on the highest few (next to the knee's blurred edge, where reliable pixels
    come and go), and reads closer to the truth (simulated demo boards, 20 µm/px: σ 7.6
    → 4.6 µm, bias −8.5 → −3.5 µm); the percentile stands in when fewer than
    :data:`HEEL_FIT_MIN_PIXELS` foot pixels are reliable. When that solder climbs more than 20 µm above the lead's
    nominal top, it is the joint's max height (``max_method`` "foot") — unless only the
    foot's first pixels, within :attr:`MeasureContext.mixing_mm` of the heel, bear it
    out (the knee's edge blends into them: a dry heel reads like a short meniscus) and
    the side strip reads the joint under its minimum (:func:`_heel_beyond_knee`).
    Otherwise it is estimated from the side fillets: the side region's percentile
    divided by ``side_fillet_ratio``. This is a calibration, not a model: the strip
    beside a lead (0.09 mm on an SOIC pad) is narrower than the focus window, and
    shape from focus reads about half the height where the solder wets the lead (0.45–
    0.5 on the synthetic boards at 20 µm/px, 5-px window: default 0.5); on an ideal
    height map the percentile of a concave strip reads ~0.8 of it.
Colour
    When the all-in-focus image is in colour, ``bare_fraction`` is the fraction of the
    visible pad (not under the body or lead) whose chromaticity is closer to the bare
    finish's than to neutral solder grey: 1 for an unsoldered ENIG or OSP pad, 0 for a
    wetted one. The finish's chroma comes from the fiducials or, without them, from the
    pads that are mostly coloured themselves (:func:`pad_chroma_reference`). NaN when
    the finish is itself grey (HASL) or no pad looks bare. On a gull-wing,
    ``heel_bare_fraction`` is the same over the pad beside the lead from the body to a
    third of the foot, where a heel fillet wets.
Plausibility
    Pad and gap pixels higher than plausible solder (chips: body top + 0.25 mm;
    gull-wing: lead top at the mould exit + 0.1 mm) are treated as unreliable (spurious focus peaks, e.g. at the end of the stack on dark or specular
    spots); the body checks still see them.
Gaps
    Between neighbouring pads of a component (the same side of a gull-wing part, along
    the lead feet; along both body sides between the two pads of a chip) the gap,
    ``gap_margin_mm`` away from the pads and ``body_margin_mm`` away from the body, is
    cut into paths running from one pad to the other. A path is covered at height z
    when ``bridge_min_fraction`` of its reliable pixels stand higher; ``gap_mm`` is the
    highest covered z over the paths. A path with fewer than half its pixels reliable
    has no level of its own (a specular web is often mostly unreliable); the reliable
    pixels of all such paths of a gap (of one side of a chip) are pooled instead, and
    their covered level is ``gap_sparse_mm`` (with at least
    :data:`MIN_SPARSE_GAP_PIXELS` of them). Along a chip's sides the band between the
    body's nominal edge and ``body_margin_mm`` is read too (a web that wets the body
    lies mostly there), with the measured body left out; a path there counts only where it is level
    (its median within ``bridge_height_mm`` of its covered z: a path straddling the
    body's edge mixes body and board heights) and stands at least
    :data:`LEVEL_PATH_BODY_GAP_MM` below the measured body top (the body's bled edge).
    Within the mixing reach of the body's edge (:attr:`MeasureContext.mixing_mm`: half
    the focus window + 2 px; the whole band at 20 µm/px with a 5-px window) a level is
    only evidence of a possible web (``gap_blend_mm``): the edge's focus outweighs the
    board's weak texture in every window there, and its height blends into theirs.
Area, volume, mean
    Over the solder area (chips: the pad outside the grown body; gull-wing: the side
    region plus the solder standing above the nominal lead top on the foot); volume and
    area scaled by 1/reliable fraction for the pixels that could not be measured.
Uncertainty
    Per pixel ``u = σ_F² · ε / (√2 · Δd)``: the standard deviation of the 3-point
    Gaussian peak position when the log focus values carry a relative noise ε
    (``focus_noise``), σ_F the fitted focus-curve width (``Surface.sigma_mm``), Δd the
    focus step. Meniscus F: the fit's standard error combined with
    ``√Σ(g²u²)/Σg²`` (g the model's shape) and the local level's uncertainty.
    Percentile max: median ``u`` of the pixels at or above the percentile ⊕ level.
    Heel fillet: the fit's standard error ⊕ ``√Σ(g²u²)/Σg²`` ⊕ the lead level's ⊕ level.
    Mean: ``√Σu²/n`` ⊕ level. Volume: ``p²·√Σu²`` ⊕ level × area. Area: the area of
    the pixels within ``u`` of the coverage threshold.
Component (body)
    Reliable fraction of the body footprint; the raised blob (above the presence
    threshold) found near the nominal body, its size relative to the body (presence)
    and offset of its centre (the midpoint of its edges along the part's axes, BOARD
    frame); for chips the tilt of a plane fitted to the body top between the
    terminations, where the blob stands, and the area standing far above the nominal
    top (an upright, tombstoned part); the share of the body and pads inside the
    measured field. Other parts' footprints are never taken into a body.
Gull-wing lead
    ``toe_mm``: the median height just beyond the toe (``body_margin_mm`` to +0.15 mm);
    a raised lead with nothing up to its underside there is the lead itself lifted, and
    its foot is then never taken for solder (``max_method`` "side").
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np

from ._config import InspectConfig
from ._features import body_blob, presence_threshold_mm
from ._geometry import apply2d, arc_fillet, pixel_to_world, polygon_mask, world_to_pixel
from ._reference import body_top_mm, lead_top_mm

log = logging.getLogger(__name__)

__all__ = ["ComponentMeasurement", "JointMeasurement", "MeasureContext", "measure_board"]

NAN = float("nan")


@dataclass
class JointMeasurement:
    """Raw numbers of one joint (before any rule is applied)."""

    joint_id: str
    world_xy_mm: tuple[float, float]
    n_pixels: int
    reliable_fraction: float
    max_mm: float = NAN
    max_method: str = ""            # "meniscus", "percentile", "foot", "side"
    mean_mm: float = NAN
    u_max_mm: float = NAN
    u_mean_mm: float = NAN
    volume_mm3: float = NAN
    u_volume_mm3: float = NAN
    area_mm2: float = NAN
    u_area_mm2: float = NAN
    lead_mm: float = NAN            # gull-wing: the lead's own height (toe half of the foot)
    lead_n: int = 0                 # ... and the reliable pixels it is the median of
    lead_spread_mm: float = NAN     # ... and their spread (1.4826 MAD)
    foot_reliable_fraction: float = NAN
    foot_mm: float = NAN            # gull-wing: percentile over the foot
    heel_fit_n: int = 0             # gull-wing: reliable foot pixels the heel meniscus is fitted to
    heel_reach_mm: float = NAN      # ... and how far along the foot the fitted meniscus runs
    heel_mm: float = NAN            # ... the heel fillet's top it gives
    heel_far_mm: float = NAN        # ... the same fit over the foot beyond the knee's mixing reach
    side_mm: float = NAN            # gull-wing: percentile over the side region
    side_level_mm: float = NAN      # ... and its median (the solder level beside the foot)
    cap_mm: float = NAN             # chip: end-cap top above its nominal height
    toe_mm: float = NAN             # gull-wing: solder just beyond the toe (median)
    in_field_fraction: float = 1.0  # share of the pad inside the measured field
    fillet_reach: float = NAN       # chip meniscus: fraction of F the fitted pixels reach
    fillet_near_mm: float = NAN     # ... how near the termination they come (5th pct)
    fillet_edge_mm: float = NAN     # ... where its solder area starts (+ a pixel)
    observed_mm: float = NAN        # the solder area's percentile (what the pixels show)
    fit_seen_mm: float = NAN        # chip meniscus: the same over the pixels the fit kept
    bulge_mm: float = NAN           # chip, bulging fillet: the concave fit's height (overshoots)
    min_reads_mm: float = NAN       # chip meniscus: the lowest F a fillet at the minimum reads
    bare_fraction: float = NAN      # visible pad looking like bare finish (colour)
    heel_bare_fraction: float = NAN  # gull-wing: the same beside the lead by the heel
    clipped_fraction: float = NAN   # solder area clipped white in the all-in-focus image
    gap_mm: float = NAN             # highest covered level towards a neighbour
    gap_neighbour: str = ""
    gap_fraction: float = NAN
    gap_sparse_mm: float = NAN      # covered level of the pooled pixels of sparse paths
    gap_sparse_n: int = 0           # ... and how many pixels that is
    gap_sparse_neighbour: str = ""
    gap_blend_mm: float = NAN       # chip: a level path within the body edge's mixing reach
    gap_blend_neighbour: str = ""
    gap_unread: str = ""            # a neighbour the gap to which is not read at all
    gap_glint: float = NAN          # largest share of a gap path's pixels clipped white
    gap_glint_neighbour: str = ""
    level_mm: float = 0.0           # local board level removed
    polygon_px: np.ndarray | None = field(default=None, repr=False)


@dataclass
class ComponentMeasurement:
    ref: str
    reliable_fraction: float        # of the body where it stands (else its footprint)
    present_fraction: float
    body_height_mm: float
    offset_mm: tuple[float, float]
    tilt_deg: float
    standing_fraction: float
    n_pixels: int
    in_field_fraction: float = 1.0  # share of the body and pads inside the measured field
    tilt_pixels: int = 0            # body pixels the tilt was fitted to
    body_mask: np.ndarray | None = field(default=None, repr=False)   # (H, W) the blob
    #: chips: the body top's plane, h = a·x + b·y + c in the part's own frame (mm, above
    #: the local board), and twice the standard error of its height at the end caps
    top_plane: tuple[float, float, float] | None = None
    top_plane_u2_mm: float = NAN
    #: how far the body's middle may lie from the offset read, along the part's own x
    #: and y (its blob's ends could not be told apart: :func:`_body_middle`)
    offset_slack_mm: tuple[float, float] = (0.0, 0.0)
    #: (2, 2) covariance (mm², BOARD frame) of where the placement puts the part, from
    #: the registration's fit (:func:`._features.position_covariance`); None: not known
    offset_cov_mm2: np.ndarray | None = field(default=None, repr=False)
    #: gull-wing parts: how far the body is turned from its nominal rotation (deg,
    #: counter-clockwise; :func:`_body_turn`), NaN where not measured
    turn_deg: float = NAN


@dataclass
class MeasureContext:
    """The maps every measurement reads.

    Attributes
    ----------
    height : (H, W) float64
        Heights above the global board plane (mm).
    reliable : (H, W) bool
    u_px : (H, W) float64
        Per-pixel height uncertainty (mm; NaN when unknown).
    bare : (H, W) bool
        Reliable pixels of the bare board (outside every footprint).
    T : (3, 3)
        Placement WORLD = T · BOARD.
    p : float
        Pixel size (mm).
    u_plane_mm : float
        Uncertainty of the global plane's level.
    chroma : (H, W) float32 or None
        (R − B) / (R + G + B) of the all-in-focus image (None for grey images).
    bare_chroma : float
        Chroma of the bare pad finish (fiducials, else the pads' own colour, see
        :func:`pad_chroma_reference`); NaN when unknown or neutral.
    field : (H, W) bool or None
        Where the measurement exists (the aligned field of view); None: everywhere.
    clipped : (H, W) bool or None
        Pixels clipped white in the all-in-focus image
        (:func:`smdinspect.sff.clipped_white`); None: not known.
    window_px : int
        The focus window the heights were measured with (0: true heights, no window).
    """

    height: np.ndarray
    reliable: np.ndarray
    u_px: np.ndarray
    bare: np.ndarray
    T: np.ndarray
    p: float
    u_plane_mm: float
    chroma: np.ndarray | None = None
    bare_chroma: float = NAN
    field: np.ndarray | None = None
    clipped: np.ndarray | None = None
    window_px: int = 0

    @property
    def mixing_mm(self) -> float:
        """How far (mm) a height step's two depths mix in the heights measured next to
        it: half the focus window, the operator's own reach (a 3-px Laplacian) and the
        in-focus blur (about a pixel). Within it a pixel's window holds the step's
        edge, whose focus outweighs weak texture: its height is a blend, not the
        surface's (0 for true heights)."""
        return (self.window_px // 2 + 2) * self.p if self.window_px else 0.0

    def in_field(self, poly_board: np.ndarray) -> float:
        """Share of a BOARD polygon's area inside the image and the measured field."""
        px = self.to_px(poly_board)
        x, y = px[:, 0], px[:, 1]
        area_px = 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y)))
        if area_px < 1.0:
            return 1.0
        m = polygon_mask(px, self.shape)
        if self.field is not None:
            m &= self.field
        return float(min(1.0, m.sum() / area_px))

    @property
    def shape(self) -> tuple[int, int]:
        return self.height.shape  # type: ignore[return-value]

    def to_px(self, poly_board: np.ndarray) -> np.ndarray:
        """BOARD polygon → image (col, row)."""
        return world_to_pixel(apply2d(self.T, poly_board), shape=self.shape, pixel_size_mm=self.p)

    def mask(self, poly_board: np.ndarray) -> np.ndarray:
        return polygon_mask(self.to_px(poly_board), self.shape)

    def board_to_px(self, xy_board) -> np.ndarray:
        return self.to_px(np.asarray(xy_board, np.float64).reshape(-1, 2))

    def px_to_board(self, cols, rows) -> np.ndarray:
        world = pixel_to_world(np.column_stack([cols, rows]), shape=self.shape,
                               pixel_size_mm=self.p)
        return apply2d(np.linalg.inv(self.T), world)


def pixel_uncertainty(sigma_mm: np.ndarray, step_mm: float, focus_noise: float) -> np.ndarray:
    """``u = σ_F² · ε / (√2 · Δd)`` per pixel (mm); NaN where σ_F is not finite."""
    s = np.asarray(sigma_mm, np.float64)
    if not (step_mm and np.isfinite(step_mm) and step_mm > 0):
        return np.full(s.shape, NAN)
    return s * s * float(focus_noise) / (math.sqrt(2.0) * float(step_mm))


def chroma_map(aif: np.ndarray) -> np.ndarray | None:
    """``(R − B) / (R + G + B)`` of an RGB image (None for grey ones)."""
    img = np.asarray(aif)
    if img.ndim != 3 or img.shape[2] != 3:
        return None
    f = img.astype(np.float32)
    s = f.sum(axis=2)
    return np.where(s > 0, (f[:, :, 0] - f[:, :, 2]) / np.maximum(s, 1e-6), 0.0).astype(np.float32)


def fiducial_chroma(board, T, chroma: np.ndarray | None, p: float) -> tuple[float, bool]:
    """Median chroma inside the fiducials (the bare pad finish) and whether any fiducial
    was seen; the chroma is NaN when none was seen or the finish is grey (HASL, tin)."""
    if chroma is None or not board.fiducials:
        return NAN, False
    vals = []
    shape = chroma.shape
    for f in board.fiducials:
        r = 0.35 * f.diameter_mm
        t = np.linspace(0, 2 * np.pi, 32, endpoint=False)
        circ = np.column_stack([f.x_mm + r * np.cos(t), f.y_mm + r * np.sin(t)])
        m = polygon_mask(world_to_pixel(apply2d(T, circ), shape=shape, pixel_size_mm=p), shape)
        if m.sum() >= 5:
            vals.append(chroma[m])
    if not vals:
        return NAN, False
    c = float(np.median(np.concatenate(vals)))
    return (c if abs(c) >= COLOURED_CHROMA else NAN), True


#: A pixel is "coloured" (not neutral solder or tin grey) when its chroma magnitude is
#: at least this; ENIG and OSP copper read 0.2–0.35, solder and tin < 0.03.
COLOURED_CHROMA = 0.08


def pad_chroma_reference(board, T, chroma: np.ndarray | None, p: float, *,
                         min_fraction: float = 0.5) -> float:
    """Chroma of the bare finish from the pads themselves (no fiducials needed).

    Solder and tin are neutral grey; a bare ENIG (gold) or OSP (copper) pad is
    coloured. The pads whose visible area (eroded by 2 px from the outline) is mostly
    coloured (at least ``min_fraction`` of pixels with ``|chroma| >=``
    :data:`COLOURED_CHROMA`) show the bare finish; the median chroma of their coloured
    pixels is the reference. NaN when no pad looks bare (nothing to compare: the
    colour cue stays off) or the image is grey.
    """
    if chroma is None:
        return NAN
    vals = []
    shape = chroma.shape
    for j in board.joints():
        m = polygon_mask(world_to_pixel(apply2d(T, j.polygon_mm), shape=shape,
                                        pixel_size_mm=p), shape)
        m = _morph(m, 2, grow=False)
        if m.sum() < 20:
            continue
        c = chroma[m]
        col = np.abs(c) >= COLOURED_CHROMA
        # Bare pads: mostly coloured; the body or lead covers part of any pad, so the
        # test is on the pad's coloured share of what is not grey-dark.
        if col.mean() >= min_fraction * 0.6:
            vals.append(c[col])
    if not vals:
        return NAN
    c = float(np.median(np.concatenate(vals)))
    return c if abs(c) >= COLOURED_CHROMA else NAN


def _morph(mask: np.ndarray, radius_px: float, *, grow: bool) -> np.ndarray:
    """Dilate (``grow``) or erode a bool mask by a disk of ``radius_px``."""
    import cv2

    r = int(math.ceil(radius_px))
    if r <= 0:
        return mask
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    op = cv2.dilate if grow else cv2.erode
    return op(mask.astype(np.uint8), k).astype(bool)


def _rss(values: np.ndarray) -> float:
    v = values[np.isfinite(values)]
    return float(np.sqrt(np.sum(v * v))) if v.size else NAN


def _hypot(*vals: float) -> float:
    v = [x for x in vals if np.isfinite(x)]
    return float(math.sqrt(sum(x * x for x in v))) if v else NAN


def footprints(board, ctx: MeasureContext, margin_px: float) -> dict[str, np.ndarray]:
    """Mask per component of everything it puts on the board (body, leads, pads), grown."""
    out = {}
    for comp in board.components:
        m = ctx.mask(comp.body_polygon_mm())
        for j in comp.joints:
            m |= ctx.mask(j.polygon_mm)
            if comp.kind == "gullwing":
                m |= ctx.mask(comp.termination_polygon_mm(j.id))
        out[comp.ref] = _morph(m, margin_px, grow=True)
    return out


# --------------------------------------------------------------------------------------
# A component's window: every pixel near it in component-local coordinates.
# --------------------------------------------------------------------------------------


def _half_extent(comp, direction) -> float:
    """How far the body reaches from the component centre along a unit ``direction``."""
    centred = comp.body_polygon_mm() - [comp.x_mm, comp.y_mm]
    return float(np.abs(centred @ np.asarray(direction, np.float64)).max())


def _solder_ceiling_mm(comp) -> float:
    """Highest plausible solder: chips 0.25 mm over the body top (solder over the end
    cap); gull-wing 0.1 mm over the lead's top where it leaves the mould."""
    if comp.kind == "gullwing" and comp.lead:
        return float(comp.lead["exit_height_mm"]) + float(comp.lead["thickness_mm"]) + 0.1
    return body_top_mm(comp) + 0.25


class _Win:
    """Pixels of a rectangle around a component, with component-local coordinates."""

    def __init__(self, comp, ctx: MeasureContext, level: float, grow_mm: float):
        pts = [comp.body_polygon_mm()] + [j.polygon_mm for j in comp.joints]
        if comp.kind == "gullwing":
            pts += [comp.termination_polygon_mm(j.id) for j in comp.joints]
        px = ctx.board_to_px(np.vstack(pts))
        g = grow_mm / ctx.p + 2
        H, W = ctx.shape
        c0 = int(max(math.floor(px[:, 0].min() - g), 0))
        c1 = int(min(math.ceil(px[:, 0].max() + g) + 1, W))
        r0 = int(max(math.floor(px[:, 1].min() - g), 0))
        r1 = int(min(math.ceil(px[:, 1].max() + g) + 1, H))
        # a part wholly outside the image keeps a few pixels of window at the edge
        # (none of them its own): its measurements are then empty, never an error
        c0, r0 = min(c0, max(W - 3, 0)), min(r0, max(H - 3, 0))
        c1, r1 = max(c1, min(c0 + 3, W)), max(r1, min(r0 + 3, H))
        self.sl = (slice(r0, max(r1, r0)), slice(c0, max(c1, c0)))
        self.origin = np.array([c0, r0], np.float64)
        rows, cols = np.mgrid[r0:max(r1, r0), c0:max(c1, c0)]
        self.shape = rows.shape
        b = ctx.px_to_board(cols.ravel(), rows.ravel())
        loc = comp.to_local(b)
        self.lx = loc[:, 0].reshape(self.shape)
        self.ly = loc[:, 1].reshape(self.shape)
        self.h = ctx.height[self.sl] - level
        self.rel_all = ctx.reliable[self.sl]
        # For solder, heights far above the part's own top are implausible (spurious
        # focus peaks at the end of the stack): treated as unreliable.
        self.rel = self.rel_all & (self.h <= _solder_ceiling_mm(comp))
        self.u = ctx.u_px[self.sl]
        self.chroma = None if ctx.chroma is None else ctx.chroma[self.sl]
        self.ctx = ctx
        self.comp = comp

    def mask(self, poly_board) -> np.ndarray:
        px = self.ctx.board_to_px(poly_board) - self.origin
        return polygon_mask(px, self.shape)

    def axes(self, joint):
        """(u, v, out_local, across_local, q0): coordinates along the joint's outward
        direction (from the component centre) and across it (from the pad's centre)."""
        a = math.radians(self.comp.rotation_deg)
        ob = np.asarray(joint.outward, np.float64)
        out = np.array([math.cos(a) * ob[0] + math.sin(a) * ob[1],
                        -math.sin(a) * ob[0] + math.cos(a) * ob[1]])
        acr = np.array([-out[1], out[0]])
        c = self.comp.to_local([joint.center_mm])[0]
        q0 = float(c @ acr)
        u = self.lx * out[0] + self.ly * out[1]
        v = self.lx * acr[0] + self.ly * acr[1] - q0
        return u, v, out, acr, q0


def measure_board(board, ctx: MeasureContext, config: InspectConfig):
    """Measure every joint and component.

    Returns
    -------
    joints : dict[str, JointMeasurement]
    components : dict[str, ComponentMeasurement]
    """
    joints: dict[str, JointMeasurement] = {}
    comps: dict[str, ComponentMeasurement] = {}
    # Every part's footprint (body, pads, leads) grown by the gap margin: a gap path of
    # one part must not run over a neighbouring part's pad or body.
    fps = footprints(board, ctx, margin_px=config.gap_margin_mm / ctx.p)
    drawn = footprints(board, ctx, margin_px=0)
    for comp in board.components:
        level, u_level = _local_level(comp, ctx, config)
        win = _Win(comp, ctx, level, grow_mm=max(config.local_plane_radius_mm, 0.5))
        near = _others(fps, comp.ref, win)
        comps[comp.ref] = cm = _measure_body(comp, ctx, win, level, config, exclude=near,
                                             own=drawn[comp.ref],
                                             theirs=_others(drawn, comp.ref, win))
        for j in comp.joints:
            if comp.kind == "gullwing" and comp.lead:
                joints[j.id] = _measure_gullwing(comp, j, win, config, level, u_level)
            else:
                joints[j.id] = _measure_chip(comp, j, win, config, level, u_level, body=cm)
        # Where the body really stands (a shifted part covers its own gap band).
        body = None if cm.body_mask is None else cm.body_mask[win.sl]
        _measure_gaps(comp, win, config, joints, others=near[win.sl], body=body,
                      body_top_mm=cm.body_height_mm)
    _check_colour_cue(joints, config)
    return joints, comps


def _check_colour_cue(joints: dict[str, JointMeasurement], config: InspectConfig) -> None:
    """Turn the colour cue off (every ``bare_fraction`` NaN) when most pads look bare.

    A bare-finish reference that makes most of a board's pads look bare describes their
    solder (a tinted solder or lighting), not a bare finish; or no pad was soldered, which
    the heights show by themselves. Either way the colour cannot tell one joint from
    another there, and a verdict resting on it would call every joint."""
    finite = [m for m in joints.values() if math.isfinite(m.bare_fraction)]
    if len(finite) < 4:
        return
    bare = sum(m.bare_fraction >= config.bare_missing_fraction for m in finite)
    if bare > len(finite) / 2:
        log.warning("%d of %d pads look like the bare finish by colour: the colour cue is "
                    "not used (a tinted solder, or no solder anywhere; the heights decide)",
                    bare, len(finite))
        for m in finite:
            m.bare_fraction = m.heel_bare_fraction = NAN


def _others(fps: dict[str, np.ndarray], ref: str, win: "_Win") -> np.ndarray:
    """(H, W) union of the other parts' footprints."""
    out = np.zeros(win.ctx.shape, bool)
    for k, fp in fps.items():
        if k != ref:
            out |= fp
    return out


def _local_level(comp, ctx: MeasureContext, config: InspectConfig) -> tuple[float, float]:
    """Median height of bare-board pixels near the component (and its uncertainty)."""
    polys = [comp.body_polygon_mm()] + [j.polygon_mm for j in comp.joints]
    pts = np.vstack(polys)
    lo, hi = pts.min(axis=0) - config.local_plane_radius_mm, pts.max(axis=0) + config.local_plane_radius_mm
    box = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]])
    near = ctx.mask(box) & ctx.bare
    vals = ctx.height[near]
    if vals.size < 30:
        return 0.0, ctx.u_plane_mm
    med = float(np.median(vals))
    mad = float(np.median(np.abs(vals - med))) * 1.4826
    return med, _hypot(1.2533 * mad / math.sqrt(vals.size), ctx.u_plane_mm)


def _percentile_max(h: np.ndarray, u: np.ndarray, pct: float) -> tuple[float, float]:
    v = float(np.percentile(h, pct))
    top = h >= v - 1e-12
    ut = u[top]
    return v, (float(np.nanmedian(ut)) if np.isfinite(ut).any() else NAN)


def _summaries(m: JointMeasurement, h: np.ndarray, u: np.ndarray, n_area: int, n_rel: int,
               p: float, config: InspectConfig, u_level: float) -> None:
    """Mean, volume and area of the solder area's reliable heights ``h``."""
    if n_rel == 0:
        return
    m.mean_mm = float(np.mean(h))
    m.u_mean_mm = _hypot(_rss(u) / n_rel, u_level)
    px_area = p * p
    scale = n_area / n_rel
    covered = h > config.solder_min_height_mm
    m.volume_mm3 = float(np.clip(h, 0.0, None).sum() * px_area * scale)
    m.area_mm2 = float(covered.sum() * px_area * scale)
    m.u_volume_mm3 = _hypot(_rss(u) * px_area * scale, u_level * m.area_mm2)
    near = np.abs(h - config.solder_min_height_mm) <= np.where(np.isfinite(u), u, 0.0)
    m.u_area_mm2 = float(near.sum() * px_area * scale)


def _bare_fraction(win: _Win, region: np.ndarray) -> float:
    ctx = win.ctx
    if win.chroma is None or not np.isfinite(ctx.bare_chroma) or region.sum() < 5:
        return NAN
    c = win.chroma[region]
    return float(np.mean(np.abs(c - ctx.bare_chroma) < np.abs(c)))


def _new(joint, win: _Win, pad: np.ndarray, level: float) -> JointMeasurement:
    ctx = win.ctx
    centre_w = apply2d(ctx.T, np.array([joint.center_mm]))[0]
    clipped = (float(np.mean(ctx.clipped[win.sl][pad])) if ctx.clipped is not None and pad.any()
               else NAN)
    return JointMeasurement(joint.id, (float(centre_w[0]), float(centre_w[1])), int(pad.sum()),
                            0.0, level_mm=level, polygon_px=ctx.board_to_px(joint.polygon_mm),
                            clipped_fraction=clipped)


def _propagated_u(g: np.ndarray, u: np.ndarray) -> float:
    """Uncertainty of the amplitude A of ``z = A·g`` (least squares) from the pixels' own
    uncertainties ``u``: √Σ(g²u²) / Σg²; NaN without any finite ``u``."""
    if not np.isfinite(u).any():
        return NAN
    return float(np.sqrt(np.nansum(g ** 2 * u ** 2)) / np.sum(g ** 2))


def _meniscus_shape(d: np.ndarray, length: float) -> np.ndarray:
    """The meniscus model's shape, ``(1 − d/length)²`` (0 beyond the toe): z = F · this."""
    return np.clip(1.0 - d / length, 0.0, 1.0) ** 2


def _meniscus(d: np.ndarray, length: float, z: np.ndarray, uz: np.ndarray,
              info: dict | None = None) -> tuple[float, float]:
    """Fit ``z = F·(1 − d/length)²`` (robust, 3-MAD trimming); returns (F, uncertainty).

    The uncertainty combines the fit's standard error with the per-pixel uncertainties
    propagated through the fit, ``√Σ(g²u²) / Σg²``.
    """
    g = _meniscus_shape(d, length)
    keep = np.ones(len(z), bool)
    F = se = NAN
    for _ in range(3):
        gk, zk = g[keep], z[keep]
        den = float(np.sum(gk * gk))
        if keep.sum() < 6 or den <= 1e-9:
            break
        F = float(np.sum(gk * zk) / den)
        r = z - F * g
        s = 1.4826 * float(np.median(np.abs(r[keep]))) + 1e-4
        se = float(np.sqrt(np.sum(r[keep] ** 2) / max(keep.sum() - 1, 1) / den))
        new = np.abs(r) <= 3 * s
        if np.array_equal(new, keep):
            break
        keep = new
    if not np.isfinite(F):
        return NAN, NAN
    if info is not None:
        r = z[keep] - F * g[keep]
        info["rel_rms"] = float(np.sqrt(np.mean(r ** 2)) / max(abs(F), 1e-3))
        # How far up the meniscus the data go: the model's height fraction at the
        # highest of the kept pixels (95th percentile of g, robust to a stray pixel).
        info["reach"] = float(np.percentile(g[keep], 95))
        info["near"] = float(np.percentile(d[keep], 5))
        info["keep"] = keep
    gk = g[keep]
    uk = uz[keep]
    uf = _propagated_u(gk, uk)
    return F, _hypot(se, uf)


def _shape_floor(d: np.ndarray, length: float, F: float, shift: float = 0.0) -> float:
    """The F the meniscus fit (:func:`_meniscus`) reads, at pixels ``d`` from the end
    face, for a fillet of true height ``F`` shaped as the most curved physical meniscus
    (:func:`arc_fillet`, curvature 1: tangent to the pad, or to the face when F > L),
    each pixel reading the arc ``shift`` mm further from the face than it lies.
    Solder's fillets are arcs (surface tension), and the parabola reads an arc lower the
    more it is curved, so this is the lowest reading of a fillet exactly at ``F`` from
    its shape alone (at the band minimum, seen from the body margin out: 0.72 of F on an
    0402's pad, 0.74 on a 1206's, 0.93-0.94 on 0603 and 0805 pads, with no shift).

    ``shift``: a window on the fillet's slope reads where its focus energy lies, and on
    a fillet rising towards the termination's bright, specular end that is outward of
    its centre: the reliable heights follow the true profile moved about a pixel away
    from the face (README, weak spots: 20-33 µm low 0.08-0.12 mm out on an 0603)."""
    g = _meniscus_shape(d, length)
    den = float(np.sum(g * g))
    if den <= 1e-12 or not F > 0:
        return NAN
    return float(np.sum(g * arc_fillet((d + shift) / length, F, length, 1.0)) / den)


def _measure_chip(comp, joint, win: _Win, config: InspectConfig, level: float,
                  u_level: float, body: ComponentMeasurement | None = None) -> JointMeasurement:
    p = win.ctx.p
    pad = win.mask(joint.polygon_mm)
    u, v, out, acr, q0 = win.axes(joint)
    hl, hw = comp.body_length_mm / 2.0, comp.body_width_mm / 2.0
    mg = config.body_margin_mm
    v_body = win.ly   # across the body axis
    grown_body = (np.abs(win.lx) <= hl + mg) & (np.abs(win.ly) <= hw + mg)
    area = pad & ~grown_body
    m = _new(joint, win, area, level)
    m.in_field_fraction = win.ctx.in_field(joint.polygon_mm)
    rel = area & win.rel
    n, n_rel = int(area.sum()), int(rel.sum())
    m.reliable_fraction = n_rel / n if n else 0.0
    visible = pad & ~((np.abs(win.lx) <= hl) & (np.abs(win.ly) <= hw))
    m.bare_fraction = _bare_fraction(win, _morph(visible, 1, grow=False))
    # End cap: the termination's top, away from the body edge; solder over it stands
    # under the plausibility ceiling like any solder (above it: spurious peaks).
    t = comp.termination_length_mm
    cap = (u >= hl - t + mg) & (u <= hl - mg) & (np.abs(v_body) <= hw - mg) & win.rel
    cap_top = body_top_mm(comp)
    if cap.sum() >= 5:
        # Against the body top's own plane where it is measured and raised (a part tilted
        # under the tombstone limit raises one cap with it: that is not solder), less
        # its 2σ; the nominal top elsewhere.
        ref = np.float64(cap_top)
        if body is not None and body.top_plane is not None and np.isfinite(body.top_plane_u2_mm):
            a, b, c = body.top_plane
            ref = np.maximum(cap_top, a * win.lx[cap] + b * win.ly[cap] + c - body.top_plane_u2_mm)
        # The cap's median: solder over a cap is a layer over its top, read alike by
        # most of its pixels (test and tuning seeds 10064-10079, 200-215: 7 of 8 caps
        # with 0.1-0.2 mm of excess read 99-189 µm at their median and their 90th
        # percentile alike), while a cap seen in a few pixels scatters (two good caps
        # seen in 7 and 31 pixels read -37 and 14 µm at the median but 64 and 75 µm at
        # the 90th percentile, and were called excess; no good cap of 441 reads over
        # 50 µm at the median).
        m.cap_mm = float(np.median(win.h[cap] - ref))
        cap_top = float(np.mean(ref))
    if n_rel < 3:
        return m
    h, uu = win.h[rel], win.u[rel]
    _summaries(m, h, uu, n, n_rel, p, config, u_level)
    pct, u_pct = _percentile_max(h, uu, config.height_percentile)
    m.max_mm, m.u_max_mm, m.max_method = pct, _hypot(u_pct, u_level), "percentile"
    m.observed_mm = pct
    if config.fillet_model == "meniscus":
        pad_u = comp.to_local(joint.polygon_mm) @ out
        length = float(pad_u.max()) - hl
        end = rel & (u >= hl + mg) & (u <= hl + length) & (np.abs(v_body) <= hw)
        if length > 2 * mg and end.sum() >= 8:
            info: dict = {}
            F, uF = _meniscus(u[end] - hl, length, win.h[end], win.u[end], info)
            m.fillet_reach = info.get("reach", NAN)
            m.fillet_near_mm, m.fillet_edge_mm = info.get("near", NAN), mg + p
            if "keep" in info:
                # what the pixels the fit kept show (the area's percentile also holds those
                # it rejected: a body's bled edge by the termination)
                m.fit_seen_mm = float(np.percentile(win.h[end][info["keep"]],
                                                    config.height_percentile))
                m.min_reads_mm = _shape_floor(u[end][info["keep"]] - hl, length,
                                              joint.min_height_mm, shift=p)
            if np.isfinite(F) and F > joint.max_height_mm and info.get("rel_rms", 0.0) > 0.1:
                # Not a meniscus: a bulging (convex) fillet fits a concave model badly
                # and the fit overshoots. Its observed percentile is a lower bound of its
                # height (the crest, by the termination, is specular and mostly
                # unmeasured); the fit, an upper one, is kept for the verdict.
                m.max_method = "percentile (bulging fillet)"
                m.bulge_mm = F
            elif np.isfinite(F):
                m.max_mm, m.u_max_mm, m.max_method = F, _hypot(uF, u_level), "meniscus"
                # A chip-end fillet wets the termination at most up to its top (solder
                # over the cap is seen there directly, as cap_mm): a meniscus fitted
                # higher is the fit overshooting, not solder.
                ceiling = cap_top + max(m.cap_mm if np.isfinite(m.cap_mm) else 0.0, 0.0)
                if F > ceiling >= pct:
                    m.max_mm, m.max_method = ceiling, "meniscus (capped at the termination top)"
    return m


#: Heel fillet fit: fewest reliable foot pixels it is fitted to (else the percentile).
HEEL_FIT_MIN_PIXELS = 20


def _heel_fit(x: np.ndarray, y: np.ndarray, clip2: float, foot_length_mm: float,
              p: float, min_reach_mm: float = 0.0):
    """Best (loss, reach, A, g, keep) of ``y = A·(1 − x/ℓ)²`` over the reach grid."""
    best = None
    for reach in np.arange(max(2 * p, min_reach_mm), foot_length_mm + 1e-9, p / 2):
        g = np.clip(1.0 - x / reach, 0.0, None) ** 2
        inside = g > 0
        if inside.sum() < 5:
            continue
        keep = inside.copy()
        A = NAN
        for _ in range(4):
            den = float(np.sum(g[keep] ** 2))
            if keep.sum() < 5 or den <= 1e-12:
                break
            A = float(np.sum(g[keep] * y[keep]) / den)
            r = y - A * g
            new = inside & (r * r <= clip2)
            if np.array_equal(new, keep):
                break
            keep = new
        if not np.isfinite(A):
            continue
        r = y - A * g
        loss = float(np.sum(np.minimum(r * r, clip2)))
        if best is None or loss < best[0]:
            best = (loss, float(reach), A, g, keep)
    return best


def _heel_fillet(x: np.ndarray, z: np.ndarray, uz: np.ndarray, lead_mm: float, *,
                 foot_length_mm: float, pixel_size_mm: float, min_reach_mm: float = 0.0,
                 info: dict | None = None) -> tuple[float, float]:
    """Heel fillet height at the heel from the foot's reliable pixels (see module doc).

    Model: the solder wets the lead up to ``lead_mm + A`` at the heel and thins along
    the foot as a concave meniscus, ``z = lead + A·(1 − x/ℓ)²`` for ``x < ℓ``, the
    lead's own top beyond (x: distance from the heel along the foot, mm). For every
    reach ℓ on a grid (half-pixel steps from 2 pixels to the foot's length) A is the
    least-squares value over the pixels within ``c`` of the model (ℓ from
    ``min_reach_mm`` when that is longer), and the ℓ with the
    smallest clipped loss ``Σ min(r², c²)`` wins (a redescending M-estimate: a stray
    pixel costs at most c²). ``c = 4 s``: first s is the robust scatter of the foot's
    far half about the lead top, then the robust scatter of the first fit's residuals.
    Returns (lead + A, uncertainty: the fit's standard error combined with
    ``√Σ(g²u²)/Σg²`` and the lead level's standard error); NaN when nothing fits.
    """
    x = np.asarray(x, np.float64)
    y = np.asarray(z, np.float64) - lead_mm
    p = float(pixel_size_mm)
    flat = x >= 0.5 * foot_length_mm
    ref = y[flat] if flat.sum() >= 3 else y
    s0 = max(1.4826 * float(np.median(np.abs(ref - np.median(ref)))), 1e-4)
    best = _heel_fit(x, y, (4.0 * s0) ** 2, foot_length_mm, p, min_reach_mm)
    if best is None:
        return NAN, NAN
    r = y - best[2] * best[3]
    s1 = max(1.4826 * float(np.median(np.abs(r))), s0)
    best = _heel_fit(x, y, (4.0 * s1) ** 2, foot_length_mm, p, min_reach_mm) or best
    _, reach, A, g, keep = best
    gk, rk = g[keep], (y - A * g)[keep]
    den = float(np.sum(gk * gk))
    se = float(np.sqrt(np.sum(rk * rk) / max(keep.sum() - 1, 1) / den))
    uk = np.asarray(uz, np.float64)[keep]
    uf = _propagated_u(gk, uk)
    u_lead = 1.2533 * s0 / math.sqrt(max(int(flat.sum()), 1))
    if info is not None:
        info.update(reach_mm=reach, n=int(keep.sum()))
    return lead_mm + A, _hypot(se, uf, u_lead)


def _heel_beyond_knee(x: np.ndarray, z: np.ndarray, uz: np.ndarray, lead_mm: float, *,
                      foot_length_mm: float, pixel_size_mm: float,
                      mixing_mm: float) -> tuple[float, float]:
    """The heel fillet's top as the foot beyond the knee's mixing reach tells it.

    The knee rises from the heel to the mould's exit, several times the lead's height;
    within :attr:`MeasureContext.mixing_mm` of the heel every focus window holds the
    knee's edge, so those pixels read a blend rising towards the heel whether solder
    wets it or not (a dry heel reads like a meniscus some 0.1 mm long). A heel fillet
    high enough to count wets the lead further out: the meniscus fitted to the foot's
    pixels beyond that reach alone, extrapolated to the heel, still stands above the
    lead. The fitted reach is at least twice the mixing reach (as much meniscus seen as
    hidden): a meniscus ending just past the blend would extrapolate a pixel's noise
    tenfold. Returns (top, its uncertainty as :func:`_heel_fillet`'s); NaN when too few
    pixels lie beyond it, or when they put the solder clearly below the lead's own top
    (no evidence either way)."""
    x = np.asarray(x, np.float64)
    far = x >= mixing_mm
    if mixing_mm <= 0 or far.sum() < HEEL_FIT_MIN_PIXELS:
        return NAN, NAN
    top, u = _heel_fillet(x[far], np.asarray(z)[far], np.asarray(uz)[far], lead_mm,
                          foot_length_mm=foot_length_mm, pixel_size_mm=pixel_size_mm,
                          min_reach_mm=2.0 * mixing_mm)
    # solder standing clearly below the lead's own top is no meniscus on it: the far
    # pixels are not the foot (an unmeasured or glinting foot), no evidence
    return (top, u) if top >= lead_mm - 0.02 else (NAN, NAN)


def _seen_next_to_lead(side: np.ndarray, rel: np.ndarray, across: np.ndarray,
                       half_width: float) -> bool:
    """Whether at least half of the inner half of the side strip (the pixels nearer the
    lead's side than the strip's middle) is reliable."""
    if not side.any():
        return False
    mid = 0.5 * (half_width + float(np.max(across[side])))
    inner = side & (across <= mid)
    return bool(inner.any() and (inner & rel).sum() >= 0.5 * inner.sum())


def under_lead(comp, m: JointMeasurement) -> tuple[float, float, str]:
    """(the lead's measured underside, the solder level next to it — just beyond its toe,
    else beside it —, where that level was read): a raised lead with the solder below its
    underside is lifted, with the solder up to it buried (rule 6)."""
    underside = m.lead_mm - float((comp.lead or {}).get("thickness_mm", 0.0))
    if np.isfinite(m.toe_mm):
        return underside, m.toe_mm, "beyond its toe"
    return underside, (m.side_level_mm if np.isfinite(m.side_level_mm) else 0.0), "beside it"


def _measure_gullwing(comp, joint, win: _Win, config: InspectConfig, level: float,
                      u_level: float) -> JointMeasurement:
    p = win.ctx.p
    lead = comp.lead
    pad = win.mask(joint.polygon_mm)
    u, v, out, acr, q0 = win.axes(joint)
    toe = float(lead["span_mm"]) / 2.0
    heel = toe - float(lead["foot_length_mm"])
    b2 = float(lead["width_mm"]) / 2.0
    g_t = lead_top_mm(comp)
    half_body = _half_extent(comp, joint.outward)
    mg = config.body_margin_mm
    foot = (u >= heel) & (u <= toe - p) & (np.abs(v) <= b2 - p)
    lead_grown = (u >= half_body - p) & (u <= toe + p) & (np.abs(v) <= b2 + p)
    # Beside the foot and beyond the toe only: the knee rises to the mould's exit height
    # and its blurred edge would read as solder.
    side = pad & ~lead_grown & (u >= heel + mg)
    region = side | foot
    m = _new(joint, win, region, level)
    m.in_field_fraction = win.ctx.in_field(joint.polygon_mm)
    rel = region & win.rel
    n, n_rel = int(region.sum()), int(rel.sum())
    m.reliable_fraction = n_rel / n if n else 0.0
    visible = pad & ~lead_grown & (u >= half_body)
    m.bare_fraction = _bare_fraction(win, _morph(visible, 1, grow=False))
    # beside the lead from the body to a third of the foot: where a heel fillet wets
    m.heel_bare_fraction = _bare_fraction(
        win, _morph(visible & (u <= heel + (toe - heel) / 3.0), 1, grow=False))
    # Just beyond the toe (clear of the toe's blurred edge): a wetted lead's toe fillet
    # or the solder burying a foot stands here; a lifted lead leaves only the low dome.
    beyond = pad & win.rel & (u >= toe + mg) & (u <= toe + mg + 0.15) & (np.abs(v) <= b2)
    if beyond.sum() >= 5:
        m.toe_mm = float(np.median(win.h[beyond]))
    fr = foot & win.rel
    m.foot_reliable_fraction = float(fr.sum() / max(foot.sum(), 1))
    if fr.sum() >= 5:
        m.foot_mm, u_foot = _percentile_max(win.h[fr], win.u[fr], config.height_percentile)
        toe_half = fr & (u >= 0.5 * (heel + toe))
        if toe_half.sum() >= 3:
            h_toe = win.h[toe_half]
            m.lead_mm = float(np.median(h_toe))
            m.lead_n = int(toe_half.sum())
            m.lead_spread_mm = 1.4826 * float(np.median(np.abs(h_toe - m.lead_mm)))
    else:
        u_foot = NAN
    sr = side & win.rel
    u_side = NAN
    if sr.sum() >= 3:
        m.side_mm, u_side = _percentile_max(win.h[sr], win.u[sr], config.height_percentile)
        m.side_level_mm = float(np.median(win.h[sr]))
    if n_rel < 3:
        return m
    # Solder: the side region, plus what stands above the nominal lead top on the foot.
    hs = win.h[sr]
    hf = np.clip(win.h[fr] - g_t, 0.0, None)
    _summaries(m, np.concatenate([hs, hf]), np.concatenate([win.u[sr], win.u[fr]]), n, n_rel,
               p, config, u_level)
    # Heel fillet from the side fillets: the strip beside a lead is narrower than the
    # focus window, so its percentile reads a fraction of the wetting height.
    side_f = m.side_mm / config.side_fillet_ratio if np.isfinite(m.side_mm) else NAN
    side_u = u_side / config.side_fillet_ratio if np.isfinite(u_side) else NAN
    # A foot that stands above its nominal top with no solder up to its underside
    # (beyond the toe, else beside it) is the lead itself raised, not solder on it:
    # never a heel fillet.
    underside, below, _ = under_lead(comp, m)
    raised_lead = np.isfinite(m.lead_mm) and m.lead_mm > g_t + 0.02 and below < underside
    # The solder on the foot: its top at the heel from the meniscus fitted along the foot
    # (hundreds of pixels), not the percentile (the highest few, next to the knee's
    # blurred edge); the percentile when too few foot pixels are reliable.
    on_foot, u_on_foot, heel_n, u_far = m.foot_mm, u_foot, 0, NAN
    if fr.sum() >= HEEL_FIT_MIN_PIXELS and np.isfinite(m.lead_mm):
        heel_info: dict = {}
        hf_mm, u_hf = _heel_fillet(u[fr] - heel, win.h[fr], win.u[fr], m.lead_mm,
                                   foot_length_mm=toe - heel, pixel_size_mm=p, info=heel_info)
        if np.isfinite(hf_mm):
            on_foot, u_on_foot, heel_n = hf_mm, u_hf, int(fr.sum())
            m.heel_reach_mm, m.heel_mm = heel_info.get("reach_mm", NAN), hf_mm
            m.heel_far_mm, u_far = _heel_beyond_knee(
                u[fr] - heel, win.h[fr], win.u[fr], m.lead_mm, foot_length_mm=toe - heel,
                pixel_size_mm=p, mixing_mm=win.ctx.mixing_mm)
    # Solder that wets the heel wets the pad beside the foot too: a heel reading with the
    # side region at bare-pad level (below missing_height_mm) is the knee's blurred edge
    # on a dry foot, not a fillet (tuning boards 8-47: good joints' side percentile
    # 56 µm and up, 1 165 joints; missing joints' 30 µm and under, two of them read a
    # 'heel fillet' of 35-40 µm that way and one passed).
    # The low reading must be a measurement up to the lead, though: a steep fillet up the
    # lead's side reads as a wall in a focal sweep and leaves the pixels next to the lead
    # unreliable, so a strip measured only at its outer edge reads low on a good joint.
    side_bare = (np.isfinite(m.side_mm) and m.side_mm < config.missing_height_mm
                 and _seen_next_to_lead(side, win.rel, np.abs(v), b2))
    # A heel reading the foot beyond the knee's mixing reach does not bear out (the fit
    # there stays under 20 µm above the nominal lead top by twice its uncertainty) may
    # be the knee's edge blended into a dry heel: it is no evidence against the side strip,
    # and where the strip reads the joint under its minimum, the strip's reading
    # stands. (Where the strip passes it too, the foot's reading is kept: it varies
    # less between sweeps.)
    knee_blend = (np.isfinite(m.heel_far_mm) and m.heel_far_mm + 2 * u_far <= g_t + 0.02
                  and np.isfinite(side_f) and side_f < joint.min_height_mm)
    if (np.isfinite(on_foot) and on_foot > g_t + 0.02 and not raised_lead and not side_bare
            and not knee_blend):
        m.max_mm, m.u_max_mm, m.max_method = on_foot, _hypot(u_on_foot, u_level), "foot"
        m.heel_fit_n = heel_n
    elif np.isfinite(side_f):
        m.max_mm, m.u_max_mm, m.max_method = side_f, _hypot(side_u, u_level), "side"
    return m


# --------------------------------------------------------------------------------------
# Gaps between pads (bridges).
# --------------------------------------------------------------------------------------


#: The band next to a chip's body reads the body's own height where the body's edge
#: bleeds into it (its rounded top edge stands up to some tens of µm below the body's
#: median height): a level path there counts as a web only this far below the body top.
LEVEL_PATH_BODY_GAP_MM = 0.1


#: Reliable pixels the sparse paths of a gap must pool for their level to count.
MIN_SPARSE_GAP_PIXELS = 10


def _path_level(h: np.ndarray, valid: np.ndarray, config: InspectConfig, *,
                level: bool = False, below_mm: float = NAN):
    """(best covered level over the paths (rows) of a (n_paths × n_along) grid, the
    share of that path above ``bridge_height_mm``, the reliable heights of the paths
    too sparsely measured to have a level of their own).

    With ``level`` a path counts only where its heights are level along it: the median
    stands within ``bridge_height_mm`` of the covered height (a web's top runs along
    the body at one height; a path that straddles the body's edge mixes the body's
    heights with the board's), and below ``below_mm`` (NaN: no bound; a sparse path's
    pixels at or above it are left out: the body's bled edge).

    Beyond the body margin (not ``level``) a path's level counts only as far as a path
    next to it (a pixel away) stands too: every height is read through a focus window
    several pixels wide, so solder standing across the gap raises the paths beside its
    crest as well, and a level seen in one path alone, its neighbours at the board, is a
    run of stray peaks, not a surface (test seed dense 10125: one path beside an 0402's
    body at 73 µm between paths at 16 and 10 µm had called both its joints bridged). A
    neighbour too sparsely measured to have a level of its own lends it the same
    quantile of what it has (however few its pixels: requiring 3 lost a true bridge,
    test seed dense 10108 C3). In the band next to a chip's body (``level``) a web that
    wets the body's side may show in a single path beyond its edge, the rest of it under
    the body's margin: there one path's level counts alone."""
    q = 1.0 - config.bridge_min_fraction
    n = len(h)
    own = np.full(n, NAN)   # each path's level (NaN: none)
    lend = np.full(n, NAN)  # what each path lends its neighbours (not ``level``)
    frac = np.full(n, NAN)
    sparse = []
    for k, (hk, ok) in enumerate(zip(h, valid)):
        vals = hk[ok]
        if vals.size < max(3, 0.5 * ok.size):
            kept = vals[vals < below_mm] if level and np.isfinite(below_mm) else vals
            sparse.append(kept)
            if kept.size and not level:
                lend[k] = float(np.quantile(kept, q))
            continue
        if level:
            z, mid, top = np.quantile(vals, [q, 0.5, config.bridge_min_fraction])
            if mid - z > config.bridge_height_mm or not top < below_mm:
                continue
        else:
            z = np.quantile(vals, q)
        own[k] = lend[k] = float(z)
        frac[k] = float(np.mean(vals > config.bridge_height_mm))
    best_z, best_f = NAN, NAN
    for k in np.flatnonzero(np.isfinite(own)):
        z = own[k]
        if not level:
            beside = [lend[i] for i in (k - 1, k + 1) if 0 <= i < n and np.isfinite(lend[i])]
            if not beside:
                continue
            z = min(z, max(beside))
        if not np.isfinite(best_z) or z > best_z:
            best_z, best_f = z, frac[k]
    return best_z, best_f, (np.concatenate(sparse) if sparse else np.empty(0))


def _record(joints, a: str, b: str, z: float, f: float, sparse: np.ndarray,
            config: InspectConfig) -> None:
    """Keep the gap's levels on both joints when higher than what they hold."""
    zs = (float(np.quantile(sparse, 1.0 - config.bridge_min_fraction))
          if sparse.size >= MIN_SPARSE_GAP_PIXELS else NAN)
    for jid, other in ((a, b), (b, a)):
        m = joints[jid]
        if np.isfinite(z) and not z <= m.gap_mm:
            m.gap_mm, m.gap_neighbour, m.gap_fraction = z, other, f
        if np.isfinite(zs) and not zs <= m.gap_sparse_mm:
            m.gap_sparse_mm, m.gap_sparse_n, m.gap_sparse_neighbour = zs, int(sparse.size), other


def _record_unread(joints, a: str, b: str, z: float, pooled: np.ndarray,
                   open_share: float) -> None:
    """Name each joint's neighbour when their gap (one side of it) lies open to view
    (at least half of it inside the image and clear of the parts) and was still not
    read: no path with a level (``z`` NaN) and fewer than
    :data:`MIN_SPARSE_GAP_PIXELS` reliable pixels to pool — a web there (glint, steep
    sides) is neither seen nor ruled out. A gap covered by a neighbouring part's
    footprint or by the body itself is not free board, and is left as it is."""
    if open_share < 0.5 or np.isfinite(z) or pooled.size >= MIN_SPARSE_GAP_PIXELS:
        return
    for jid, other in ((a, b), (b, a)):
        joints[jid].gap_unread = joints[jid].gap_unread or other


def _record_larger(joints, a: str, b: str, value: float, name: str, neighbour: str) -> None:
    """Keep ``value`` as field ``name`` of both joints, the other one as ``neighbour``,
    where it is larger than what they hold: a gap's glint (``gap_glint``) or a level read
    where a body's edge blends into the heights (``gap_blend_mm``, a possible web)."""
    if not np.isfinite(value):
        return
    for jid, other in ((a, b), (b, a)):
        m = joints[jid]
        if not value <= getattr(m, name):
            setattr(m, name, value)
            setattr(m, neighbour, other)


def _measure_gaps(comp, win: _Win, config: InspectConfig, joints: dict[str, JointMeasurement],
                  *, others: np.ndarray | None = None, body: np.ndarray | None = None,
                  body_top_mm: float = NAN) -> None:
    """Solder across the gaps between neighbouring pads of one component (see module doc).

    ``others``: window pixels of the other parts' footprints, never sampled. ``body``:
    the window pixels of the measured body (where the body really stands: a shifted
    part covers its own gap band), kept ``body_margin_mm`` clear of except in the band
    next to a chip's body, read with ``body_top_mm`` (its measured height; see
    :func:`_path_level`)."""
    p = win.ctx.p
    gm, mg = config.gap_margin_mm, config.body_margin_mm
    hl, hw = comp.body_length_mm / 2.0, comp.body_width_mm / 2.0
    # never sampled: the other parts and the nominal and measured bodies grown by the
    # body margin (the band next to a chip's body: the bodies themselves, below)
    body_grown = (np.abs(win.lx) <= hl + mg) & (np.abs(win.ly) <= hw + mg)
    if body is not None:
        body_grown = body_grown | _morph(body, mg / p, grow=True)
    if others is not None:
        body_grown = body_grown | others
    if comp.kind == "chip" and len(comp.joints) == 2:
        # Along both long sides of the body, between the two pads' inner edges.
        a, b = comp.joints
        inner = []
        for j in (a, b):
            loc = comp.to_local(j.polygon_mm)
            inner.append(float(np.min(np.abs(loc[:, 0]))))
        x_lim = min(inner) - gm
        if x_lim <= 2 * p:
            return
        xs = np.arange(-x_lim, x_lim + 1e-9, p)
        hug = (np.abs(win.lx) <= hl) & (np.abs(win.ly) <= hw)
        for extra in (body, others):
            if extra is not None:
                hug = hug | extra
        edge = _body_edge(comp, win, hug, others)
        body_grown |= edge
        hug |= edge
        mix = win.ctx.mixing_mm
        mixed = (np.abs(win.lx) <= hl + mix) & (np.abs(win.ly) <= hw + mix)
        if body is not None and mix > 0:
            mixed |= _morph(body, mix / p, grow=True)
        for side in (-1.0, 1.0):
            ys = side * (hw + mg + np.arange(0.0, 0.1 + 1e-9, p))
            z_out, f, sparse, open_share, glint = _sample_paths(win, comp, xs, ys, body_grown,
                                                                config)
            _record(joints, a.id, b.id, z_out, f, np.empty(0), config)
            _record_larger(joints, a.id, b.id, glint, "gap_glint", "gap_glint_neighbour")
            # the band next to the body (nominal edge to body_margin_mm), where a web
            # that wets the body's side stands; the side's sparse paths pooled
            ys = side * (hw + np.arange(0.0, mg - 1e-9, p))
            below = body_top_mm - LEVEL_PATH_BODY_GAP_MM
            z, f, band, _, glint = _sample_paths(win, comp, xs, ys, hug, config, level=True,
                                                 below_mm=below)
            _record_larger(joints, a.id, b.id, glint, "gap_glint", "gap_glint_neighbour")
            if mixed.any():
                # within the mixing reach of the body's edge a level may be that edge
                # blended with the board: evidence of a possible web, not a measurement;
                # only the band beyond the reach measures one
                _record_larger(joints, a.id, b.id, z, "gap_blend_mm", "gap_blend_neighbour")
                z, f, _, _, _ = _sample_paths(win, comp, xs, ys, hug | mixed, config,
                                              level=True, below_mm=below)
            pooled = np.concatenate([sparse, band])
            _record(joints, a.id, b.id, z, f, pooled, config)
            _record_unread(joints, a.id, b.id, np.fmax(z_out, z), pooled, open_share)
        return
    groups: dict[tuple[float, float], list] = {}
    for j in comp.joints:
        key = (round(j.outward[0], 3), round(j.outward[1], 3))
        groups.setdefault(key, []).append(j)
    lead = comp.lead or {}
    b2 = float(lead.get("width_mm", 0.0)) / 2.0
    cc = np.array([comp.x_mm, comp.y_mm])
    # Along the feet only: the knees rise to the mould exit and blur sideways.
    heel = float(lead.get("span_mm", 0.0)) / 2.0 - float(lead.get("foot_length_mm", 0.0))
    for key, js in groups.items():
        out_b = np.array(key, np.float64)
        out_b /= np.linalg.norm(out_b)
        acr_b = np.array([-out_b[1], out_b[0]])
        js = sorted(js, key=lambda j: float(np.dot(j.center_mm, acr_b)))
        half_body = _half_extent(comp, out_b)
        for a, b in zip(js[:-1], js[1:]):
            pa, pb = np.asarray(a.polygon_mm), np.asarray(b.polygon_mm)
            u0 = max(float(((pa - cc) @ out_b).min()), float(((pb - cc) @ out_b).min()),
                     half_body + mg, heel + mg)
            u1 = min(float(((pa - cc) @ out_b).max()), float(((pb - cc) @ out_b).max()))
            # Between the pads, clear of both pads and of the leads on them.
            ca = float(np.dot(np.asarray(a.center_mm) - cc, acr_b))
            cb = float(np.dot(np.asarray(b.center_mm) - cc, acr_b))
            v0 = max(float(((pa - cc) @ acr_b).max()), ca + b2) + gm
            v1 = min(float(((pb - cc) @ acr_b).min()), cb - b2) - gm
            if u1 - u0 < 2 * p or v1 - v0 < 2 * p:
                continue
            us = np.arange(u0 + p / 2, u1, p)
            vs = np.arange(v0, v1 + 1e-9, p / 2)
            pts = (cc[None, None, :] + out_b[None, None, :] * us[:, None, None]
                   + acr_b[None, None, :] * vs[None, :, None])
            z, f, sparse, open_share, glint = _sample_board(win, pts, body_grown, config)
            _record(joints, a.id, b.id, z, f, sparse, config)
            _record_larger(joints, a.id, b.id, glint, "gap_glint", "gap_glint_neighbour")
            _record_unread(joints, a.id, b.id, z, sparse, open_share)


def _body_edge(comp, win: _Win, footprint: np.ndarray, others: np.ndarray | None) -> np.ndarray:
    """Reliable pixels standing at the body's height (above its presence threshold) in
    blobs that reach into its ``footprint`` (nominal and measured; never into the
    ``others``' footprints): the body's own edge, whether or not its blob is the one
    :func:`body_blob` picked. A chip's top is weakly textured, so its reliable pixels
    are often a ring along its edges cut from the middle by unreliable ones, and the
    window's reading of the edge spreads a few pixels past it (tuning demo 251, an
    0805: a strip 0.06-0.12 mm beyond the nominal side, read 450-500 µm with the body
    top at 520 µm, cut off from the picked blob and read as a bridge by the gap's
    paths). Solder across the gap stands far
    below that threshold (standoff + 0.8 × the body's height)."""
    import cv2

    tall = win.rel_all & (win.h > presence_threshold_mm(comp))
    if others is not None:
        tall &= ~others
    if not tall.any():
        return tall
    n, lab = cv2.connectedComponents(tall.view(np.uint8), connectivity=8)
    hit = np.zeros(n, bool)
    hit[np.unique(lab[tall & footprint])] = True
    hit[0] = False
    return hit[lab]


def _sample_paths(win: _Win, comp, xs, ys, exclude, config, **level):
    """Sample the grid of component-local points (paths along x, one per y)."""
    gx, gy = np.meshgrid(xs, ys)           # rows: paths (one y each), cols: along x
    pts = comp.to_board(np.column_stack([gx.ravel(), gy.ravel()])).reshape(gx.shape + (2,))
    return _sample_board(win, pts, exclude, config, **level)


def _sample_board(win: _Win, pts: np.ndarray, exclude: np.ndarray, config: InspectConfig,
                  **level):
    """Paths are the rows of the BOARD point grid ``pts`` (n_paths, n_along, 2);
    ``level`` as in :func:`_path_level`. Returns its three values, the share of the
    grid open to be read (inside the image, not excluded) and the largest share of a
    path's open pixels clipped white (:func:`_glint_share`)."""
    shp = pts.shape[:2]
    cr = win.ctx.board_to_px(pts.reshape(-1, 2)) - win.origin
    c = np.round(cr[:, 0]).astype(int)
    r = np.round(cr[:, 1]).astype(int)
    H, W = win.shape
    inside = (c >= 0) & (c < W) & (r >= 0) & (r < H)
    c, r = np.clip(c, 0, W - 1), np.clip(r, 0, H - 1)
    open_ = inside & ~exclude[r, c]
    valid = (open_ & win.rel[r, c]).reshape(shp)
    h = np.where(valid, win.h[r, c].reshape(shp), np.nan)
    clipped = win.ctx.clipped
    glint = NAN if clipped is None else _glint_share(open_.reshape(shp),
                                                     clipped[win.sl][r, c].reshape(shp))
    return (*_path_level(h, valid, config, **level), float(open_.mean()), glint)


#: A path needs this many open pixels for its clipped share to count.
MIN_GLINT_PATH_PIXELS = 3


def _glint_share(open_: np.ndarray, clipped: np.ndarray) -> float:
    """The largest share, over the paths (rows) with at least
    :data:`MIN_GLINT_PATH_PIXELS` open pixels, of a path's open pixels clipped white;
    NaN when no path has that many.

    The gap between two pads is laminate or solder mask, which scatters light: it is not
    clipped white where the pads and the solder are exposed right. Specular metal is: a
    path from pad to pad that glints along most of its length is metal across the gap,
    a web of solder whose glint leaves its heights unmeasured (the reliable pixels
    pooled beside it then read the board, and a bridge would pass)."""
    n = np.count_nonzero(open_, axis=1)
    k = np.count_nonzero(open_ & clipped, axis=1)
    ok = n >= MIN_GLINT_PATH_PIXELS
    return float(np.max(k[ok] / n[ok])) if ok.any() else NAN


# --------------------------------------------------------------------------------------
# Bodies.
# --------------------------------------------------------------------------------------


#: A blob whose ends cannot be told apart (both or neither seen) gives the body's middle
#: halfway between them when it spans at least this share of what a whole body spans;
#: the half of what it lacks is carried as the middle's slack (``offset_slack_mm``), which
#: a shift must clear. A moulded body's edges are sparse in the blob (chamfer, depth
#: edge): on tuning seeds 28-47, 49 of 246 judged parts, nearly every SOIC and TSSOP, had
#: no middle, so no shift check (demo 41: an SOIC-8 0.41 mm off, its leads standing in
#: the gaps called bridges).
BODY_SEEN_SPAN = 0.8


def _body_middle(win: _Win, lo: np.ndarray, hi: np.ndarray, size: np.ndarray,
                 top_mm: float, p: float) -> tuple[np.ndarray, np.ndarray]:
    """The body's middle in the part's frame (x, y), from its blob's extent ``lo`` ..
    ``hi`` on each axis, and its slack (how far off it may be); NaN on an axis where it
    is not seen.

    The body is rigid and its ``size`` known. Its blob's 2nd..98th percentiles span 96 %
    of it, less a pixel and up to the mixing reach at each end
    (:attr:`MeasureContext.mixing_mm`: there the body's height blends into its
    surroundings' and may fall below the presence level); where the blob spans that
    much the middle is halfway between the ends. A shorter blob stops where the
    measurement stops (an unreliable body middle) at one end or both: an end is seen
    where the 3 px beyond it, across the blob, are mostly reliable and below ``top_mm``
    (the body's edge, down to the board or the solder), and the middle is then half the
    size from the seen end. With both ends seen or neither, the middle is halfway
    between them if the blob spans :data:`BODY_SEEN_SPAN` of a whole body, with half
    the shortfall as slack; else NaN.
    """
    mid = (lo + hi) / 2.0
    slack = np.zeros(2)
    local = (win.lx, win.ly)
    for ax in (0, 1):
        full = 0.96 * size[ax] - 2 * (win.ctx.mixing_mm + p)
        if hi[ax] - lo[ax] >= full:
            continue
        u, v = local[ax], local[1 - ax]
        across = (v >= lo[1 - ax]) & (v <= hi[1 - ax])
        seen = []
        for end, sign in ((hi[ax], 1.0), (lo[ax], -1.0)):
            strip = across & (sign * (u - end) > 0) & (sign * (u - end) <= 3 * p)
            rel = strip & win.rel_all
            seen.append(rel.sum() >= 0.5 * max(strip.sum(), 1)
                        and np.mean(win.h[rel] < top_mm) >= 0.5)
        if seen[0] and not seen[1]:
            mid[ax] = hi[ax] - size[ax] / 2.0
        elif seen[1] and not seen[0]:
            mid[ax] = lo[ax] + size[ax] / 2.0
        elif hi[ax] - lo[ax] >= BODY_SEEN_SPAN * full:
            slack[ax] = (full - (hi[ax] - lo[ax])) / 2.0
        else:
            mid[ax] = NAN
    return mid, slack


def _measure_body(comp, ctx: MeasureContext, win: _Win, level: float,
                  config: InspectConfig, *, exclude: np.ndarray, own: np.ndarray,
                  theirs: np.ndarray) -> ComponentMeasurement:
    """Presence, centroid offset, tilt and upright area of the component body.

    ``exclude``: the other parts' footprints, grown by the gap margin (image-sized);
    ``own`` / ``theirs``: this part's and the other parts' footprints as drawn (image-
    sized), which decide whose a tall blob reaching into ``exclude`` is.

    The raised body is searched in a window around the nominal body (grown by twice
    the shift tolerance + 0.2 mm): the connected blob of pixels above the presence
    threshold that overlaps the nominal body most, holes filled
    (:func:`._features.body_blob`). Presence is the blob's reliable pixels relative to
    the reliable pixels of the nominal body, so a shifted body still counts as present.
    """
    p = ctx.p
    hl, hw = comp.body_length_mm / 2.0, comp.body_width_mm / 2.0
    mg = config.body_margin_mm
    inner = (np.abs(win.lx) <= hl - mg) & (np.abs(win.ly) <= hw - mg)
    n = int(inner.sum())
    rel = inner & win.rel_all
    n_rel = int(rel.sum())
    frac = float(n_rel / n) if n else 0.0
    # Chips: far enough for a part shifted by its own width (other parts' footprints
    # are excluded, so a neighbour is never taken for it).
    radius = max(config.shift_tol_mm, config.shift_tol_fraction * comp.body_width_mm) * 2 + 0.2
    if comp.kind == "chip":
        radius = max(radius, min(comp.body_width_mm, comp.body_length_mm) + 0.2)
    blob = body_blob(comp, ctx.height, ctx.reliable, ctx.T, p, search_mm=radius, level=level,
                     exclude=exclude)
    if blob is None:
        blob = np.zeros(ctx.shape, bool)
    br = blob & ctx.reliable
    present = float(min(1.0, br.sum() / n_rel)) if n_rel else 0.0
    if n_rel:
        # Also every reliable pixel of the nominal body standing at body height, in one
        # blob or not: where few of a body's pixels are reliable they are scattered
        # islands that no closing joins, and the blob holds one of them (independent
        # renderer, test demo 10108 C1: 19 % of the body reliable, 95 % of it at body
        # height, the blob 39 %: called missing). Only the body's top can be seen inside
        # its footprint, so these are no less the body's than the blob's pixels.
        standing = rel & (win.h > presence_threshold_mm(comp))
        present = max(present, float(standing.sum() / n_rel))
    body_h = float(np.median(ctx.height[br] - level)) if br.any() else NAN
    offset = (NAN, NAN)
    slack = np.zeros(2)
    rows, cols = np.nonzero(blob)
    if rows.size >= 10:
        # The body's centre from its edges (2nd and 98th percentiles of the blob along
        # the part's own axes), not the blob's centroid: unreliable patches inside the
        # body or solder merged at one end do not move the edges.
        loc = comp.to_local(ctx.px_to_board(cols, rows))
        lo, hi = np.percentile(loc, 2, axis=0), np.percentile(loc, 98, axis=0)
        mid, slack = _body_middle(win, lo, hi, np.array([hl, hw]) * 2,
                                  presence_threshold_mm(comp), p)
        if np.isfinite(mid).all():
            cen = comp.to_board([mid])[0]
            offset = (float(cen[0] - comp.x_mm), float(cen[1] - comp.y_mm))
            # How much of the body is measured, where it stands: a part shifted off its
            # footprint leaves the nominal one half board and pad, weakly textured or
            # specular (tuning demo 42: an 0805 1.01 mm off read 1.03 mm from its edges
            # with 26 % of the nominal footprint reliable, and passed unchecked).
            at = (np.abs(win.lx - mid[0]) <= hl - mg) & (np.abs(win.ly - mid[1]) <= hw - mg)
            if at.any():
                frac = float((at & win.rel_all).sum() / at.sum())
    tilt = NAN
    standing = 0.0
    n_tilt = 0
    plane, u2 = None, NAN
    if comp.kind == "chip":
        # The body between the terminations: solder over an end cap (excess) never
        # reaches it, so its top plane is the body's own (a tilted part tilts it).
        t = comp.termination_length_mm
        middle = (np.abs(win.lx) <= max(hl - t - 0.02, 0.25 * hl)) & \
            (np.abs(win.ly) <= hw - mg) & win.rel_all
        wb = blob[win.sl]
        half_middle = max(hl - t - 0.05, 0.25 * hl)   # the middle's half-length, in a blob
        if wb.sum() >= 20:
            # The middle of the body where it really stands (a shifted or turned part),
            # from the blob's own extent along the part's axis.
            # Along the part: the nominal middle (solder over a cap lengthens the blob);
            # across it: where the blob stands (a shifted part), both trimmed a little
            # more for a turned part.
            y0, y1 = np.percentile(win.ly[wb], [2, 98])
            yc = (y0 + y1) / 2
            middle = wb & (np.abs(win.lx) <= half_middle) & \
                (np.abs(win.ly - yc) <= max((y1 - y0) / 2 - mg, 0.25 * (y1 - y0) / 2)) & \
                win.rel_all
        floor = 0.5 * body_top_mm(comp)
        tilt, n_tilt, plane, u2 = _body_tilt(win, middle, floor_mm=floor, at_x_mm=hl - t / 2.0,
                                             min_span_mm=half_middle)
        lift = 0.25 * comp.body_length_mm * math.sin(math.radians(tilt))  # half of (L/2)·sin θ
        if plane is not None and tilt > config.tombstone_tilt_deg \
                and plane[2] - body_top_mm(comp) < lift:
            # A chip tilted by θ pivots on its low end, so its middle stands (L/2)·sin θ
            # above the nominal top; a middle at the nominal top (less than half that) is
            # a level body whose measured slope is borrowed from solder piled at one end
            # (test seeds dense 10064 and 10068, demo 10078: 0402s with 0.16-0.2 mm of
            # excess over one cap read 8-10 deg with their middles 2-6 µm from the
            # nominal top, where the tilt would put them 73-83 µm above it; the true
            # tombstones read over 8 deg on these and tuning boards 200-215 stand
            # 318-1274 µm above it).
            # The body is then level: its plane along the part is the middle's median.
            sel = middle & (win.h > floor)
            plane = (0.0, plane[1], float(np.median(win.h[sel] - plane[1] * win.ly[sel])))
            tilt = 0.0
        # An upright part stands far above the nominal top over much of its footprint, or,
        # stood on end (up to 90 deg), on its end pad up to a body height beyond the
        # body's end; a tall blob that reaches into another part's footprint is that part
        # (a neighbour tombstoned towards this one leans over its end).
        top = body_top_mm(comp)
        reach = hl + max(0.1, comp.body_height_mm + 0.1)
        near = (np.abs(win.lx) <= reach) & (np.abs(win.ly) <= hw + 0.1) & win.rel_all
        tall = win.rel_all & (win.h > top + max(0.2, 0.3 * comp.body_height_mm))
        if tall.any():
            import cv2

            _, lab = cv2.connectedComponents(tall.view(np.uint8), connectivity=8)
            for k in np.unique(lab[tall & exclude[win.sl]]):
                blob_k = lab == k
                # whose: a part stood on end stands on its own pad and leans from it (a
                # neighbour tombstoned towards this one lies more on its own footprint
                # than on this one's; this part, stood up leaning towards a close
                # neighbour, more on its own: test seed dense 10007, an 0402 at 83 deg
                # 0.2 mm from an 0603's pad, had been left standing unseen)
                if (blob_k & theirs[win.sl]).sum() >= (blob_k & own[win.sl]).sum():
                    tall &= ~blob_k
        tall &= near
        standing = float(tall.sum() * p * p / (comp.body_length_mm * comp.body_width_mm))
    in_field = min([ctx.in_field(comp.body_polygon_mm())]
                   + [ctx.in_field(j.polygon_mm) for j in comp.joints])
    if standing < config.standing_fraction and _runs_out(blob, rows, cols, ctx.field):
        # The body as it stands runs out of the measured field (a part moved towards its
        # edge): what is inside is at most the blob (tuning demo 21: an 0805 1.24 mm off,
        # 10 % of it inside, was read `component_missing` from that sliver). A part stood
        # up is judged on what stands in view (test demo 10008: an 0805 at 75° leaning
        # out of the image, 27 % of its area far above its top).
        in_field = min(in_field, rows.size * p * p / (comp.body_length_mm * comp.body_width_mm))
    turn = _body_turn(comp, loc) if comp.kind == "gullwing" and rows.size >= 10 else NAN
    return ComponentMeasurement(comp.ref, frac, present, body_h, offset, tilt, standing, n,
                                in_field_fraction=in_field, tilt_pixels=n_tilt,
                                body_mask=blob if blob.any() else None,
                                top_plane=plane, top_plane_u2_mm=u2,
                                offset_slack_mm=(float(slack[0]), float(slack[1])),
                                turn_deg=turn)


def _body_turn(comp, loc: np.ndarray) -> float:
    """How far a body is turned from its nominal rotation (deg, counter-clockwise), from
    the smallest rectangle around its blob (``loc``: the blob's pixels in the part's
    own frame, mm); NaN unless that rectangle has the body's size within 20 % (a blob
    cut by the field or merged with something else has no meaningful orientation).

    A gull-wing part turned by θ moves its outer leads sideways by up to half its lead
    span times sin θ whatever its centre does (an SOIC-8 at 4°: 0.19 mm, half a lead's
    width), which the centre's offset alone does not show.
    """
    import cv2

    (_, _), (w, h), angle = cv2.minAreaRect(np.asarray(loc, np.float32))
    size = sorted((comp.body_length_mm, comp.body_width_mm))
    if not all(abs(a - b) <= 0.2 * b for a, b in zip(sorted((w, h)), size)):
        return NAN
    # the rectangle's rotation, folded to within ±45° of the part's own axes
    return float((angle + 45.0) % 90.0 - 45.0)


def _runs_out(mask: np.ndarray, rows: np.ndarray, cols: np.ndarray,
              field: np.ndarray | None) -> bool:
    """Whether an image-sized ``mask`` (its pixels at ``rows``, ``cols``) touches the
    image's border or, with ``field``, a pixel outside the measured field (8-neighbours)."""
    if rows.size == 0:
        return False
    H, W = mask.shape
    r0, r1, c0, c1 = rows.min(), rows.max(), cols.min(), cols.max()
    if r0 == 0 or c0 == 0 or r1 == H - 1 or c1 == W - 1:
        return True
    if field is None:
        return False
    import cv2

    sl = (slice(r0 - 1, r1 + 2), slice(c0 - 1, c1 + 2))
    grown = cv2.dilate(mask[sl].view(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    return bool((grown & ~field[sl]).any())


def _body_tilt(win: _Win, rel: np.ndarray, *, floor_mm: float = 0.1,
               at_x_mm: float = 0.0,
               min_span_mm: float = 0.0) -> tuple[float, int, tuple | None, float]:
    """Tilt (deg) along the component's axis of a plane fitted to the raised body pixels,
    the number of pixels it was fitted to, the plane (a, b, c: h = a·x + b·y + c in the
    part's frame) and twice the standard error of its height at x = ±``at_x_mm``, y = 0
    (the larger of the two ends).

    Pixels lower than ``floor_mm`` are left out (a tombstoned chip's lower end exposes
    the pad); the fit is a robust least-squares plane (two passes). The pixels it keeps
    must span ``min_span_mm`` along the axis: a plane through a strip a pixel or two
    wide across the body has no measured slope along it (tuning seed dense 205: an
    0402's 11 pixels 26 µm apart read 68.5° and made a good part a tombstone), so the
    tilt and the plane are then unknown (NaN, None)."""
    sel = rel & (win.h > floor_mm)
    if sel.sum() < 10:
        return NAN, int(sel.sum()), None, NAN
    x, y, z = win.lx[sel], win.ly[sel], win.h[sel]
    A = np.column_stack([x, y, np.ones(len(z))])
    keep = np.ones(len(z), bool)
    coef = np.zeros(3)
    s = NAN
    for _ in range(2):
        coef = np.linalg.lstsq(A[keep], z[keep], rcond=None)[0]
        res = z - A @ coef
        s = 1.4826 * np.median(np.abs(res[keep])) + 1e-6
        keep = np.abs(res) <= 3 * s
        if keep.sum() < 10:
            break
    if keep.any() and float(np.ptp(x[keep])) < min_span_mm:
        return NAN, int(sel.sum()), None, NAN
    u2 = NAN
    if keep.sum() >= 10:
        cov = np.linalg.pinv(A[keep].T @ A[keep]) * s * s
        u2 = 2.0 * math.sqrt(max(float(g @ cov @ g) for g in
                                 (np.array([at_x_mm, 0.0, 1.0]), np.array([-at_x_mm, 0.0, 1.0]))))
    return (float(math.degrees(math.atan(abs(coef[0])))), int(sel.sum()),
            tuple(float(c) for c in coef), u2)
