"""Fine registration from features: component body centres and fiducial circles.

After the coarse search (error up to a few tens of µm and a few tenths of a degree),
every component body and fiducial gives one point pair (nominal BOARD position,
measured WORLD position):

* **Body centre**: the connected blob of reliable pixels standing above the body's
  presence threshold near the nominal body, holes filled; used only when its area (of
  its convex hull: notches along a termination do not count) is close to the body's
  nominal area (a shifted, tombstoned or missing part either fails
  this or is rejected later as an outlier). A gull-wing body gives its blob's centroid;
  a chip the midpoint of its blob's extents along and across its length, with an
  uncertainty along the length from how much the blob's ends changed
  (:func:`_chip_position`: a termination lost to glint or solder heaped over one moves
  the midpoint along the chip, not across it). Both are immune to symmetric edge blur.
* **Fiducial**: in the all-in-focus image, the fiducial's edge is found along rays from
  the predicted centre (strongest radial gradient, either polarity, sub-pixel) and a
  circle is fitted to the edge points (algebraic fit, then outliers dropped); used when
  its radius matches the board file.

Bodies are searched up to :data:`BODY_SEARCH_MM` from where the coarse placement puts
them (the blob of plausible area nearest to the prediction), since the coarse match can
lock onto one large shifted part (an IC) and leave every other part that far off.
A consensus (every two pairs propose a rigid transform; the one most pairs agree with
within :data:`CONSENSUS_MM` wins, a chip's residual along its length counted in units of
its uncertainty there) removes such a part before a weighted least-squares rigid
transform is fitted to the agreeing pairs (each weighed in each direction by its
uncertainty, :func:`fit_pairs`), with iterative rejection
of the worst pair while it is off by more than ``max(3 × median residual, 30 µm)``, its
residual taken off the fit of the others (deletion residual: a biased body pulls the fit
of all towards itself). Fiducials weigh 20 times
more than bodies (see :data:`FIDUCIAL_WEIGHT`).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from ._geometry import apply2d, pixel_to_world, polygon_mask, world_to_pixel
from ._reference import body_top_mm, lead_top_mm

__all__ = ["FeaturePair", "feature_pairs", "fit_rigid2d"]

log = logging.getLogger(__name__)

#: Weights in the rigid fit. Fiducial centres are found to ~1 µm on the synthetic
#: boards; body centres carry 10–40 µm of bias from asymmetric fillets and edge blur,
#: so they only matter when fewer than two fiducials are seen.
FIDUCIAL_WEIGHT = 1.0
BODY_WEIGHT = 0.05
#: A chip body's position error across its length on a clean blob (mm): the scale by
#: which its uncertainty along the length is measured (:func:`_chip_position`).
BODY_SIGMA_MM = 0.015
#: How far from its predicted position a body is searched (mm).
BODY_SEARCH_MM = 0.6
#: Pairs within this of a candidate transform agree with it (mm).
CONSENSUS_MM = 0.06


@dataclass(frozen=True)
class FeaturePair:
    kind: str                    # "body" or "fiducial"
    id: str
    board_xy: tuple[float, float]
    world_xy: tuple[float, float]
    weight: float = 1.0
    #: A chip body: the unit vector (WORLD) along its length, and its position's
    #: uncertainty along the length relative to across it (≥ 1; see
    #: :func:`_chip_position`). None: the position is known alike in every direction.
    axis: tuple[float, float] | None = None
    along_sigma: float = 1.0

    def information(self) -> np.ndarray:
        """(2, 2) the pair's weight in the rigid fit, in each direction."""
        m = np.eye(2)
        if self.axis is not None:
            u = np.asarray(self.axis)
            m -= (1.0 - self.along_sigma ** -2) * np.outer(u, u)
        return self.weight * m


def presence_threshold_mm(comp) -> float:
    """Height above which a pixel counts as the component's body (mm above the board).

    Chips: standoff + 80 % of the body height (above a nominal fillet, which reaches
    60 %). Gull-wing: halfway between the lead top and the body top.
    """
    if comp.kind == "chip":
        return float(comp.standoff_mm + 0.8 * comp.body_height_mm)
    return 0.5 * (body_top_mm(comp) + lead_top_mm(comp))


def _search_window(comp, shape, T, p, search_mm: float):
    """The body's footprint grown by ``search_mm``, as placed by ``T``, cropped to the
    image: ``(sub, window, c0, r0)`` (slices, bool mask within them, crop origin), or
    None when less than 3 px of it lie in the image."""
    hl, hw = comp.body_length_mm / 2 + search_mm, comp.body_width_mm / 2 + search_mm
    win_b = comp.to_board([[-hl, -hw], [hl, -hw], [hl, hw], [-hl, hw]])
    win_px = world_to_pixel(apply2d(T, win_b), shape=shape, pixel_size_mm=p)
    c0, r0 = np.floor(win_px.min(axis=0)).astype(int) - 1
    c1, r1 = np.ceil(win_px.max(axis=0)).astype(int) + 2
    c0, r0, c1, r1 = max(c0, 0), max(r0, 0), min(c1, shape[1]), min(r1, shape[0])
    if c1 - c0 < 3 or r1 - r0 < 3:
        return None
    return ((slice(r0, r1), slice(c0, c1)),
            polygon_mask(win_px - [c0, r0], (r1 - r0, c1 - c0)), c0, r0)


def body_blob(comp, height, reliable, T, p, *, search_mm: float,
              level: float = 0.0, exclude: np.ndarray | None = None) -> np.ndarray | None:
    """Mask of the measured body of ``comp`` (holes filled), or None when not found.

    ``level``: the local board level, subtracted from ``height`` (only inside the
    search window). ``exclude``: (H, W) pixels never part of the blob (the other
    parts' footprints, so a neighbour's body or a tombstone leaning over is not
    merged into this one)."""
    import cv2
    from scipy.ndimage import binary_fill_holes

    shape = height.shape
    found = _search_window(comp, shape, T, p, search_mm)
    if found is None:
        return None
    sub, window, c0, r0 = found
    body_px = world_to_pixel(apply2d(T, comp.body_polygon_mm()), shape=shape, pixel_size_mm=p)
    body = polygon_mask(body_px - [c0, r0], window.shape)
    cand = window & reliable[sub] & (height[sub] - level > presence_threshold_mm(comp))
    if exclude is not None:
        window = window & ~exclude[sub]
        cand &= window
    if not cand.any():
        return None
    # Close thin unreliable seams (e.g. where an end cap meets the body) before labelling.
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (7, 7))
    cand = cv2.morphologyEx(cand.astype(np.uint8), cv2.MORPH_CLOSE, k).astype(bool) & window
    n, lab = cv2.connectedComponents(cand.astype(np.uint8), connectivity=8)
    counts = np.bincount(lab[body & cand], minlength=n)
    counts[0] = 0
    if counts.max() > 0:
        pick = int(np.argmax(counts))
    else:
        # Shifted off its footprint altogether: the blob of at least half the body's
        # area nearest to the nominal centre.
        centre = body_px.mean(axis=0) - [c0, r0]
        area = np.bincount(lab.ravel(), minlength=n)
        best = np.inf
        pick = 0
        for i in range(1, n):
            if area[i] * p * p < 0.5 * comp.body_length_mm * comp.body_width_mm:
                continue
            rr, cc = np.nonzero(lab == i)
            d = float(np.hypot(cc.mean() - centre[0], rr.mean() - centre[1]))
            if d < best:
                best, pick = d, i
        if pick == 0:
            return None
    blob = binary_fill_holes(lab == pick)
    out = np.zeros(shape, bool)
    out[sub] = blob
    return out


def _body_pair(comp, height, reliable, T, p, *,
               search_mm: float = BODY_SEARCH_MM) -> FeaturePair | None:
    """The blob of about the body's area (convex hull, :func:`_area_matches`) nearest to
    the predicted centre."""
    import cv2
    from scipy.ndimage import binary_fill_holes

    shape = height.shape
    found = _search_window(comp, shape, T, p, search_mm)
    if found is None:
        return None
    sub, window, c0, r0 = found
    cand = window & reliable[sub] & (height[sub] > presence_threshold_mm(comp))
    if not cand.any():
        return None
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (7, 7))
    cand = cv2.morphologyEx(cand.astype(np.uint8), cv2.MORPH_CLOSE, k).astype(bool) & window
    n, lab = cv2.connectedComponents(cand.astype(np.uint8), connectivity=8)
    smallest = min(L * Wd for L, Wd in _body_shapes(comp))
    pred = world_to_pixel(apply2d(T, np.array([[comp.x_mm, comp.y_mm]])), shape=shape,
                          pixel_size_mm=p)[0] - [c0, r0]
    best, best_d = None, np.inf
    for i in range(1, n):
        blob = lab == i
        if blob.sum() * p * p < 0.5 * smallest:
            continue
        blob = binary_fill_holes(blob)
        rows, cols = np.nonzero(blob)
        if not _area_matches(comp, _hull_area_px(np.column_stack([cols, rows])
                                                 .astype(np.float32)) * p * p):
            continue
        # A blob cut by the search window's edge is not the whole body.
        if rows.min() == 0 or cols.min() == 0 or rows.max() == blob.shape[0] - 1 or \
                cols.max() == blob.shape[1] - 1:
            continue
        c = np.array([cols.mean(), rows.mean()])
        d = float(np.hypot(*(c - pred)))
        if d < best_d:
            best, best_d = (c, rows, cols), d
    if best is None:
        return None
    c, rows, cols = best
    if comp.kind != "chip":
        x, y = pixel_to_world(np.array([c + [c0, r0]]), shape=shape, pixel_size_mm=p)[0]
        return FeaturePair("body", comp.ref, (comp.x_mm, comp.y_mm), (float(x), float(y)),
                           weight=BODY_WEIGHT)
    xy = pixel_to_world(np.column_stack([cols + c0, rows + r0]), shape=shape, pixel_size_mm=p)
    a = math.radians(comp.rotation_deg)
    u = T[:2, :2] @ [math.cos(a), math.sin(a)]
    u /= np.hypot(*u)
    found = _chip_position(xy, u, comp.body_length_mm, comp.body_width_mm,
                           comp.termination_length_mm or 0.25 * comp.body_length_mm)
    if found is None:
        return None
    (x, y), along_sigma = found
    return FeaturePair("body", comp.ref, (comp.x_mm, comp.y_mm), (x, y), weight=BODY_WEIGHT,
                       axis=(float(u[0]), float(u[1])), along_sigma=along_sigma)


def _chip_position(xy: np.ndarray, u: np.ndarray, length_mm: float, width_mm: float,
                   termination_mm: float) -> tuple[tuple[float, float], float] | None:
    """A chip body's centre from its blob's pixels ``xy`` (WORLD mm), ``u`` the unit
    vector along its length: the midpoint of the blob's extents along and across, and
    how much less well it is known along than across (≥ 1); None when the blob is
    shorter than the body without both its terminations.

    Shape from focus grows a body's blob by the same edge bleed all round, which the
    midpoint of the extents ignores (as the centroid does, but the centroid also moves
    with every notch the focus leaves in the blob's outline). Along its length a chip's
    blob may also lose its terminations' metal, in part or whole (a glinting
    termination is unreliable), or gain solder heaped over a termination (it stands
    above the body's presence threshold), and which end changed cannot be told from
    the blob. The change Δ shows as the blob's growth along the length differing from
    its growth across (the edge bleed alone grows both alike). A gain moves the midpoint
    by up to Δ/2; a loss of up to a termination at each end, by up to
    min(|Δ|, 2·termination − |Δ|)/2 (both terminations lost leave the ceramic middle,
    centred). The position's uncertainty along is :data:`BODY_SIGMA_MM` plus that bound,
    in units of :data:`BODY_SIGMA_MM`. A blob that lost more than both terminations is
    not the body lying where it should (a tombstone's standing end).
    """
    v = np.array([-u[1], u[0]])
    pa, pc = xy @ u, xy @ v
    mid_a = 0.5 * (float(pa.min()) + float(pa.max()))
    mid_c = 0.5 * (float(pc.min()) + float(pc.max()))
    change = (float(np.ptp(pa)) - length_mm) - (float(np.ptp(pc)) - width_mm)
    if change < -2.0 * (termination_mm + BODY_SIGMA_MM):
        return None
    bias = 0.5 * (change if change >= 0 else min(-change, max(2 * termination_mm + change, 0.0)))
    x, y = mid_a * u + mid_c * v
    return (float(x), float(y)), 1.0 + bias / BODY_SIGMA_MM


def _hull_area_px(pts: np.ndarray) -> float:
    """Area (pixels) of a blob's convex hull, ``pts`` its (x, y) pixel centres (float32).

    A body is convex: its hull is not cut by the unreliable notches shape from focus
    leaves along a bright termination, where the blob's own pixel count is. The hull of
    the pixel centres is grown by half a pixel along its perimeter."""
    import cv2

    hull = cv2.convexHull(pts)
    return float(cv2.contourArea(hull) + 0.5 * cv2.arcLength(hull, True) + 1.0)


def _fiducial_pair(fid, aif_gray, T, p) -> FeaturePair | None:
    H, W = aif_gray.shape
    c = world_to_pixel(apply2d(T, np.array([[fid.x_mm, fid.y_mm]])), shape=(H, W),
                       pixel_size_mm=p)[0]
    found = _circle_edge(aif_gray, c, fid.diameter_mm / 2 / p)
    if found is None:
        return None
    x, y = pixel_to_world(np.array([found]), shape=(H, W), pixel_size_mm=p)[0]
    return FeaturePair("fiducial", fid.id, (fid.x_mm, fid.y_mm), (float(x), float(y)),
                       weight=FIDUCIAL_WEIGHT)


def _circle_edge(aif_gray, c, r: float) -> tuple[float, float] | None:
    """Centre (column, row) of the circle of radius ``r`` px near pixel ``c``: the
    strongest edge of one polarity along 72 rays from ``c`` (0.5 r to 1.5 r, or to 1.25 r
    by the image's border), fitted by a circle (three passes dropping the outliers);
    None unless its radius is within 20 % of ``r`` and its edge points lie within
    0.75 px RMS of it."""
    import cv2

    H, W = aif_gray.shape
    reach = min(1.5 * r, c[0] - 1.0, W - 2.0 - c[0], c[1] - 1.0, H - 2.0 - c[1])
    if r < 3 or reach < 1.25 * r:
        return None
    n_rays = 72
    radii = np.arange(0.5 * r, reach, 0.25)
    ang = np.linspace(0, 2 * np.pi, n_rays, endpoint=False)
    xs = (c[0] + np.cos(ang)[:, None] * radii[None, :]).astype(np.float32)
    ys = (c[1] + np.sin(ang)[:, None] * radii[None, :]).astype(np.float32)
    prof = cv2.remap(aif_gray, xs, ys, cv2.INTER_LINEAR)
    grad = np.diff(prof, axis=1)
    # One polarity for the whole circle: the sign of the mean strongest gradient.
    sign = np.sign(np.sum(grad[np.arange(n_rays), np.argmax(np.abs(grad), axis=1)]))
    if sign == 0:
        return None
    g = grad * sign
    k = np.argmax(g, axis=1)
    ok = (k > 0) & (k < g.shape[1] - 1) & (g[np.arange(n_rays), k] > 0)
    if ok.sum() < n_rays // 2:
        return None
    idx = np.arange(n_rays)[ok]
    kk = k[ok]
    a, b, cc = g[idx, kk - 1], g[idx, kk], g[idx, kk + 1]
    den = a - 2 * b + cc
    off = np.where(den < 0, 0.5 * (a - cc) / np.where(den < 0, den, -1), 0.0)
    rr = radii[0] + (kk + 0.5 + np.clip(off, -0.5, 0.5)) * 0.25
    ex = c[0] + np.cos(ang[idx]) * rr
    ey = c[1] + np.sin(ang[idx]) * rr
    keep = np.ones(len(ex), bool)
    cx = cy = rad = float("nan")
    for _ in range(3):
        A = np.column_stack([ex[keep], ey[keep], np.ones(int(keep.sum()))])
        bvec = ex[keep] ** 2 + ey[keep] ** 2
        sol = np.linalg.lstsq(A, bvec, rcond=None)[0]
        cx, cy = sol[0] / 2, sol[1] / 2
        rad = math.sqrt(max(sol[2] + cx * cx + cy * cy, 0.0))
        res = np.abs(np.hypot(ex - cx, ey - cy) - rad)
        keep = res <= max(1.0, 2.5 * float(np.median(res[keep])))
        if keep.sum() < n_rays // 3:
            return None
    if not (0.8 * r <= rad <= 1.2 * r):
        return None
    if float(np.sqrt(np.mean((np.hypot(ex[keep] - cx, ey[keep] - cy) - rad) ** 2))) > 0.75:
        return None
    return float(cx), float(cy)


#: Circles the global fiducial search keeps at most (the strongest Hough votes).
MAX_FIDUCIAL_CANDIDATES = 40


def fiducial_candidates(aif, board, p: float) -> np.ndarray:
    """(N, 2) world x, y (mm) of the round marks in the all-in-focus image that have a
    fiducial's diameter, wherever they lie: circles found by OpenCV's Hough transform
    (``HOUGH_GRADIENT_ALT``, radius within 25 % of the fiducial's), each confirmed by
    :func:`_circle_edge` (an edge of one polarity all round, radius within 20 %)."""
    import cv2

    out = []
    if aif is None or not board.fiducials:
        return np.empty((0, 2))
    gray = _gray(aif)
    g8 = np.clip(gray * 255.0, 0, 255).astype(np.uint8)
    for r in sorted({f.diameter_mm / 2.0 / p for f in board.fiducials}):
        if r < 3:
            continue
        blur = cv2.GaussianBlur(g8, (0, 0), max(1.0, r / 10.0))
        circles = cv2.HoughCircles(blur, cv2.HOUGH_GRADIENT_ALT, dp=1.5, minDist=1.5 * r,
                                   param1=100, param2=0.6, minRadius=int(0.75 * r),
                                   maxRadius=int(math.ceil(1.25 * r)))
        for x, y, _ in ([] if circles is None else circles[0][:MAX_FIDUCIAL_CANDIDATES]):
            found = _circle_edge(gray, np.array([x, y]), r)
            if found is not None:
                out.append(found)
    if not out:
        return np.empty((0, 2))
    return pixel_to_world(np.array(out), shape=gray.shape, pixel_size_mm=p)


def _gray(aif: np.ndarray) -> np.ndarray:
    img = np.asarray(aif)
    if img.ndim == 3:
        img = img.astype(np.float32).mean(axis=2)
    img = img.astype(np.float32)
    if img.max() > 0:
        img /= float(img.max())
    return img


def feature_pairs(height, reliable, aif, board, T, p) -> list[FeaturePair]:
    """Every usable body and fiducial pair under the placement ``T``."""
    pairs = []
    for comp in board.components:
        fp = _body_pair(comp, height, reliable, T, p)
        if fp is not None:
            pairs.append(fp)
    if aif is not None and board.fiducials:
        gray = _gray(aif)
        for fid in board.fiducials:
            fp = _fiducial_pair(fid, gray, T, p)
            if fp is not None:
                pairs.append(fp)
    return pairs


def fit_rigid2d(src: np.ndarray, dst: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    """Weighted least-squares rigid ``(3, 3)`` with ``dst ≈ R·src + t`` (2D Procrustes)."""
    src = np.asarray(src, np.float64)
    dst = np.asarray(dst, np.float64)
    w = np.ones(len(src)) if w is None else np.asarray(w, np.float64)
    ws = w / w.sum()
    ms, md = ws @ src, ws @ dst
    a, b = src - ms, dst - md
    C = (a * ws[:, None]).T @ b
    U, _, Vt = np.linalg.svd(C)
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    R = Vt.T @ np.diag([1.0, d]) @ U.T
    t = md - R @ ms
    T = np.eye(3)
    T[:2, :2] = R
    T[:2, 2] = t
    return T


def _normal_equations(src: np.ndarray, dst: np.ndarray, info: np.ndarray, T: np.ndarray):
    """The weighted rigid fit's linearisation at ``T``: ``(c, H, g, r)``, the predicted
    points' centroid c (the rotation's centre), the normal matrix H = Σ JᵢᵀIᵢJᵢ and
    gradient g = Σ JᵢᵀIᵢrᵢ in (tx, ty, θ), and the residuals rᵢ = dst − T·src."""
    pred = apply2d(T, src)
    c = pred.mean(axis=0)
    J = _rigid_jacobian(pred, c)
    r = dst - pred
    return (c, np.einsum("nia,nij,njb->ab", J, info, J),
            np.einsum("nia,nij,nj->a", J, info, r), r)


def _rigid_jacobian(points: np.ndarray, c: np.ndarray) -> np.ndarray:
    """(n, 2, 3): d(point)/d(tx, ty, θ) for a rotation θ about ``c`` followed by a
    translation, at each of the (n, 2) world ``points``."""
    J = np.zeros((len(points), 2, 3))
    J[:, 0, 0] = J[:, 1, 1] = 1.0
    J[:, 0, 2], J[:, 1, 2] = -(points[:, 1] - c[1]), points[:, 0] - c[0]
    return J


def fit_pairs(pairs: list[FeaturePair]) -> np.ndarray:
    """Rigid ``(3, 3)`` minimising Σ rᵢᵀ·Iᵢ·rᵢ over the pairs, rᵢ a pair's residual and
    Iᵢ its :meth:`~FeaturePair.information`: :func:`fit_rigid2d` when every pair is
    known alike in every direction, else Gauss-Newton in (rotation, translation) from
    that fit."""
    src = np.array([fp.board_xy for fp in pairs], np.float64)
    dst = np.array([fp.world_xy for fp in pairs], np.float64)
    T = fit_rigid2d(src, dst, np.array([fp.weight for fp in pairs]))
    if all(fp.axis is None or fp.along_sigma == 1.0 for fp in pairs):
        return T
    info = np.array([fp.information() for fp in pairs])
    for _ in range(10):
        c, H, g, _ = _normal_equations(src, dst, info, T)
        tx, ty, th = np.linalg.lstsq(H, g, rcond=None)[0]
        step = np.eye(3)
        step[:2, :2] = [[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]]
        step[:2, 2] = c - step[:2, :2] @ c + [tx, ty]
        T = step @ T
        if abs(th) < 1e-9 and math.hypot(tx, ty) < 1e-9:
            break
    return T


def placement_covariance(pairs: list[FeaturePair], T: np.ndarray):
    """How well the pairs fix the placement ``T`` fitted to them (:func:`fit_pairs`):
    ``(cov, centre)``, the (3, 3) covariance of a translation (mm) and a rotation
    (rad) about ``centre`` (the pairs' world centroid), s²·H⁻¹ with H = Σ JᵢᵀIᵢJᵢ the
    weighted fit's normal matrix and s² = Σ rᵢᵀIᵢrᵢ / (2n − 3) the residuals' own
    scale (the pairs' weights are relative). None without a degree of freedom or with a
    singular H."""
    n = len(pairs)
    if 2 * n - 3 <= 0:
        return None
    src = np.array([fp.board_xy for fp in pairs], np.float64)
    dst = np.array([fp.world_xy for fp in pairs], np.float64)
    info = np.array([fp.information() for fp in pairs])
    c, H, _, r = _normal_equations(src, dst, info, T)
    s2 = float(np.einsum("ni,nij,nj->", r, info, r)) / (2 * n - 3)
    try:
        cov = s2 * np.linalg.inv(H)
    except np.linalg.LinAlgError:
        return None
    return (cov, c) if np.all(np.isfinite(cov)) else None


def position_covariance(cov, centre, T: np.ndarray, board_xy) -> np.ndarray:
    """(2, 2) covariance (mm², BOARD frame) of where the placement puts the board point
    ``board_xy``, from :func:`placement_covariance`'s ``(cov, centre)``."""
    Jp = _rigid_jacobian(apply2d(T, np.asarray(board_xy, np.float64)[None]),
                         np.asarray(centre, np.float64))[0]
    S = Jp @ np.asarray(cov, np.float64) @ Jp.T
    R = T[:2, :2]
    return R.T @ S @ R


def residuals(pairs: list[FeaturePair], T: np.ndarray) -> np.ndarray:
    """How far ``T`` puts each feature from where it was measured (mm), the parts along
    and across a chip's length divided by its :attr:`~FeaturePair.along_sigma` and 1."""
    if not pairs:
        return np.zeros(0)
    src = np.array([fp.board_xy for fp in pairs], np.float64)
    d = apply2d(T, src) - np.array([fp.world_xy for fp in pairs], np.float64)
    u = np.array([fp.axis or (1.0, 0.0) for fp in pairs], np.float64)
    s = np.array([fp.along_sigma if fp.axis else 1.0 for fp in pairs], np.float64)
    along = np.einsum("ni,ni->n", d, u)
    across = d[:, 1] * u[:, 0] - d[:, 0] * u[:, 1]
    return np.hypot(along / s, across)


def _consensus(pairs: list[FeaturePair], T0: np.ndarray) -> np.ndarray:
    """Pairs agreeing with the best two-pair rigid hypothesis (or with ``T0``).

    Every two pairs at least 1 mm apart propose a transform; its support is the number
    of pairs within :data:`CONSENSUS_MM` of it (:func:`residuals`), so that
    a fiducial counts like a body here (bodies are many, fiducials few and precise).
    """
    n = len(pairs)
    src = np.array([fp.board_xy for fp in pairs])
    dst = np.array([fp.world_xy for fp in pairs])

    def support(T):
        r = residuals(pairs, T)
        agree = r <= CONSENSUS_MM
        return int(agree.sum()), -float(np.sum(np.minimum(r, CONSENSUS_MM))), agree

    best = support(T0)
    for i in range(n):
        for j in range(i + 1, n):
            if np.hypot(*(src[i] - src[j])) < 1.0:
                continue
            T = fit_rigid2d(src[[i, j]], dst[[i, j]])
            if abs(math.degrees(math.atan2(T[1, 0], T[0, 0])) -
                   math.degrees(math.atan2(T0[1, 0], T0[0, 0]))) > 2.0:
                continue
            cand = support(T)
            if cand[:2] > best[:2]:
                best = cand
    agree = best[2]
    return agree if agree.sum() >= 2 else np.ones(n, bool)


def refine_with_features(pairs: list[FeaturePair], T0: np.ndarray, *, min_pairs: int = 3,
                         max_residual_mm: float = CONSENSUS_MM):
    """Fit the placement to the feature pairs with outlier rejection.

    A pair is an outlier when its residual exceeds both 3× the median of the kept ones
    and ``max_residual_mm``: the bias a body centroid carries through shape from focus
    (:data:`CONSENSUS_MM`); with a tighter floor the fit keeps the two or three bodies
    whose biases happen to agree (small parts in one corner: a rotation 0.2° off)
    and rejects the rest of a correctly placed board.

    Returns
    -------
    T : (3, 3) or None
        None when fewer than ``min_pairs`` consistent pairs remain.
    info : dict
        Pairs used and rejected with their residuals (mm).
    """
    n_fid = sum(fp.kind == "fiducial" for fp in pairs)
    if len(pairs) < min_pairs and n_fid < 2:
        return None, {"pairs": len(pairs), "reason": f"only {len(pairs)} features found"}
    src = np.array([fp.board_xy for fp in pairs])
    keep = _consensus(pairs, T0)
    res = residuals(pairs, T0)
    T = T0

    def fit(sel: np.ndarray) -> np.ndarray:
        return fit_pairs([fp for fp, k in zip(pairs, sel) if k])

    for _ in range(len(pairs)):
        n_fid = sum(fp.kind == "fiducial" and k for fp, k in zip(pairs, keep))
        if keep.sum() < min_pairs and n_fid < 2:
            return None, {"pairs": len(pairs), "reason": "features disagree",
                          "residual_mm": np.round(res, 4).tolist()}
        T = fit(keep)
        res = residuals(pairs, T)
        lim = max(3.0 * float(np.median(res[keep])), max_residual_mm)
        worst = int(np.argmax(np.where(keep, res, -1.0)))
        if res[worst] <= lim and keep.sum() > min_pairs:
            # The worst pair pulls the fit towards itself, so its own residual
            # understates it: judge it by its deletion residual (off the fit of the
            # others) against the others' spread under that fit.
            # A pair far from the others is predicted less well by their fit (its
            # rotation error grows with the distance): the allowance grows as the
            # prediction's standard error, sqrt(1 + 1/n + d² / Σ d_j²) for a rigid fit
            # of n pairs spread Σ d_j² about their centroid, d the pair's distance.
            rest = keep.copy()
            rest[worst] = False
            r_del = residuals(pairs, fit(rest))
            c = src[rest].mean(axis=0)
            spread = float(np.sum((src[rest] - c) ** 2))
            lever = float(np.sqrt(1.0 + 1.0 / rest.sum()
                                  + float(np.sum((src[worst] - c) ** 2)) / max(spread, 1e-9)))
            if r_del[worst] <= lever * max(3.0 * float(np.median(r_del[rest])), max_residual_mm):
                break
        elif res[worst] <= lim:
            break
        keep[worst] = False
    fixed = placement_covariance([fp for fp, k in zip(pairs, keep) if k], T)
    info = {
        "covariance": None if fixed is None else {"cov": fixed[0].tolist(),
                                                  "centre": fixed[1].tolist()},
        "used": [f"{fp.kind}:{fp.id}" for fp, k in zip(pairs, keep) if k],
        "rejected": [f"{fp.kind}:{fp.id}" for fp, k in zip(pairs, keep) if not k],
        "residual_mm": {f"{fp.kind}:{fp.id}": round(float(r), 5) for fp, r in zip(pairs, res)},
        "rms_mm": round(float(np.sqrt(np.mean(res[keep] ** 2))), 5),
    }
    return T, info


# --------------------------------------------------------------------------------------
# Global pose from bodies: match measured body blobs to the reference layout.
# --------------------------------------------------------------------------------------

#: A measured blob matches a body when its convex hull's area matches the body's
#: (:func:`_area_matches`, as in the local body search) and its minimum-area rectangle's
#: sides lie within :data:`BLOB_SIDE_TOL_MM` (or 25 %) of the body's length and width
#: (through shape from focus a body's blob grows by up to ~0.2 mm across: edge blur).
BLOB_SIDE_TOL_MM = 0.25
#: Width of the band by which shape from focus grows or shrinks a body's outline (edge
#: bleed of half a focus window, unreliable notches): the area test allows it on small
#: bodies, where 0.8-1.2 of the area is less than this band.
BLOB_EDGE_MM = 0.05
#: Two bodies closer than this (mm) do not define a rotation well enough to propose one.
MIN_PAIR_SPAN_MM = 2.0


@dataclass(frozen=True)
class _Blob:
    xy: tuple[float, float]      # centroid, WORLD mm
    sides: tuple[float, float]   # min-area rectangle, long side first (mm)
    angle_deg: float             # direction of the long side, mod 180
    area_mm2: float              # convex hull (notches and holes filled)


def _measured_blobs(height, reliable, level_mm: float, p: float) -> list[_Blob]:
    """Connected reliable regions standing higher than ``level_mm`` (holes filled)."""
    import cv2
    from scipy.ndimage import binary_fill_holes

    cand = reliable & (height > level_mm)
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (7, 7))
    cand = cv2.morphologyEx(cand.astype(np.uint8), cv2.MORPH_CLOSE, k)
    n, lab, stats, _ = cv2.connectedComponentsWithStats(cand, connectivity=8)
    H, W = height.shape
    out = []
    for i in range(1, n):
        x, y, w, h, area = stats[i]
        if area * p * p < 0.05:                          # smaller than any body we know
            continue
        # A region touching the image border is cut: its centroid is not the body's.
        if x == 0 or y == 0 or x + w >= W or y + h >= H:
            continue
        blob = binary_fill_holes(lab[y:y + h, x:x + w] == i)
        rows, cols = np.nonzero(blob)
        pts = np.column_stack([cols + x, rows + y]).astype(np.float32)
        (_, _), (a, b), ang = cv2.minAreaRect(pts)
        # minAreaRect: side a along angle `ang` (image x right, y down).
        a, b = (a + 1.0) * p, (b + 1.0) * p
        if b > a:
            a, b, ang = b, a, ang + 90.0
        cx, cy = pixel_to_world(np.array([[cols.mean() + x, rows.mean() + y]]), shape=(H, W),
                                pixel_size_mm=p)[0]
        # Image y points down: a direction at image angle `ang` is at -ang in WORLD.
        out.append(_Blob((float(cx), float(cy)), (float(a), float(b)), float((-ang) % 180.0),
                         _hull_area_px(pts) * p * p))
    return out


def _body_shapes(comp) -> list[tuple[float, float]]:
    """(length, width) of what a measured blob of the body may show: the whole body and,
    for a chip, its middle between the metal end caps. The caps are plated metal,
    specular: a light that glints on them clips them white or leaves them dark, and
    shape from focus then measures the ceramic middle alone (test seed demo 10087: its
    0805 a 1.4 x 1.2 mm blob, its 0402 0.54 x 0.51 mm, against bodies of 2.0 x 1.25 and
    1.0 x 0.5 mm with caps of 0.4 and 0.25 mm). The middle's centroid is the body's."""
    L, W = comp.body_length_mm, comp.body_width_mm
    shapes = [(L, W)]
    t = comp.termination_length_mm
    if comp.kind == "chip" and 0.0 < 2 * t < L:
        shapes.append((L - 2 * t, W))
    return shapes


def _area_matches(comp, area_mm2: float) -> bool:
    """A blob's area is the body's, whole or a chip's middle (:func:`_body_shapes`)."""
    return any(_area_matches_shape(L, Wd, area_mm2) for L, Wd in _body_shapes(comp))


def _area_matches_shape(L: float, Wd: float, area_mm2: float) -> bool:
    """0.8-1.2 times the nominal area of an L x Wd rectangle, or within its outline moved
    :data:`BLOB_EDGE_MM` in or out (edge bleed is a band of fixed width: on an 0402 it
    alone adds ~25 %)."""
    e = BLOB_EDGE_MM
    nominal = L * Wd
    lo = min(0.8 * nominal, max(L - 2 * e, 0.0) * max(Wd - 2 * e, 0.0))
    hi = max(1.2 * nominal, (L + 2 * e) * (Wd + 2 * e))
    return lo <= area_mm2 <= hi


def _matched_shapes(comp, blob: _Blob) -> list[tuple[float, float]]:
    """The shapes of :func:`_body_shapes` whose area and sides the blob has."""
    a, b = blob.sides
    out = []
    for L, Wd in _body_shapes(comp):
        if not _area_matches_shape(L, Wd, blob.area_mm2):
            continue
        long, short = max(L, Wd), min(L, Wd)
        if abs(a - long) <= max(BLOB_SIDE_TOL_MM, 0.25 * long) and \
                abs(b - short) <= max(BLOB_SIDE_TOL_MM, 0.25 * short):
            out.append((L, Wd))
    return out


def _blob_matches(comp, blob: _Blob) -> bool:
    return bool(_matched_shapes(comp, blob))


def _axis_turns_with(comp, blob: _Blob, rot_deg: float, shapes=None) -> bool:
    """Whether the blob's long side lies along the long side of a shape it matches
    (``shapes``, by default :func:`_matched_shapes`) under a placement turned
    ``rot_deg`` (a blob or shape within 15 % of square says nothing).

    A chip's middle between its caps is measured as (L − 2t) along the part by the
    width grown by the edge band on each side: its sides bleed into the board while its
    caps, unmeasured, do not. So an 0402's middle (0.5 x 0.5 mm) reads long across the
    part (test seed demo 10087: 0.59 x 0.50 mm at 86° to it), an 0805's (1.2 x 1.25 mm)
    and an 0603's (1.0 x 0.8 mm) about square."""
    if blob.sides[0] <= 1.15 * blob.sides[1]:
        return True
    whole = (comp.body_length_mm, comp.body_width_mm)
    for L, Wd in (_matched_shapes(comp, blob) if shapes is None else shapes):
        if (L, Wd) != whole:
            Wd += 2 * BLOB_EDGE_MM
        if max(L, Wd) <= 1.15 * min(L, Wd):
            return True
        along = comp.rotation_deg + (0.0 if L >= Wd else 90.0)   # L lies along the part's x
        if _angle_diff(blob.angle_deg, along + rot_deg) <= 10.0:
            return True
    return False


def _angle_diff(a: float, b: float, period: float = 180.0) -> float:
    d = (a - b) % period
    return min(d, period - d)


def global_fiducial_pose(aif, board, p, *, T_nominal: np.ndarray, max_rotation_deg: float,
                         max_offset_mm: float, tol_mm: float = 0.05):
    """Placement of ``board`` from its fiducials alone, wherever the board lies in the image.

    Every two marks of :func:`fiducial_candidates` as far apart as two of the board's
    fiducials (within ``2 tol_mm``) propose a rigid placement, both ways round;
    placements turned more than ``max_rotation_deg`` or moved more than
    ``max_offset_mm`` from ``T_nominal`` (with one body-search distance to spare) are
    dropped. A placement's support is the number of fiducials with a mark within
    ``tol_mm`` of where it puts them; the best-supported one (then the smallest summed
    residual) is refitted to them by least squares. Fiducials are the board's own
    reference marks: they locate it where its parts cannot (the largest part missing,
    the others shifted, tombstoned or cut by the field edge).

    Returns
    -------
    T : (3, 3) float64 or None
        None when fewer than two fiducials agree.
    info : dict
        ``support`` (fiducial ids), ``rms_mm``, ``candidates`` (marks found),
        ``hypotheses`` (placements scored), or ``reason``.
    """
    fids = list(board.fiducials)
    marks = fiducial_candidates(aif, board, p) if len(fids) >= 2 else np.empty((0, 2))
    info: dict = {"candidates": int(len(marks)), "hypotheses": 0}
    if len(marks) < 2:
        info["reason"] = f"{len(marks)} fiducial-sized marks"
        return None, info
    ref = np.array([[f.x_mm, f.y_mm] for f in fids], np.float64)
    rot0 = math.degrees(math.atan2(T_nominal[1, 0], T_nominal[0, 0]))
    centre = np.array(board.size_mm, np.float64) / 2.0
    c_nom = apply2d(T_nominal, centre[None])[0]
    best, best_T = (0, 0.0, []), None
    for a in range(len(fids)):
        for b in range(len(fids)):
            if a == b:
                continue
            d_ref = float(np.hypot(*(ref[a] - ref[b])))
            for i in range(len(marks)):
                for j in range(len(marks)):
                    if i == j or abs(float(np.hypot(*(marks[i] - marks[j]))) - d_ref) > 2 * tol_mm:
                        continue
                    T = fit_rigid2d(ref[[a, b]], marks[[i, j]])
                    rot = math.degrees(math.atan2(T[1, 0], T[0, 0]))
                    if _angle_diff(rot, rot0, 360.0) > max_rotation_deg + 1.0:
                        continue
                    if float(np.hypot(*(apply2d(T, centre[None])[0] - c_nom))) > \
                            max_offset_mm + BODY_SEARCH_MM:
                        continue
                    info["hypotheses"] += 1
                    near = _distances(apply2d(T, ref), marks).min(axis=1)
                    keep = [k for k in range(len(fids)) if near[k] <= tol_mm]
                    score = (len(keep), -float(near[keep].sum()), keep)
                    if score[:2] > best[:2]:
                        best, best_T = score, T
    if best_T is None or best[0] < 2:
        info["reason"] = "no two fiducials agree"
        return None, info
    keep = best[2]
    dst = marks[np.argmin(_distances(apply2d(best_T, ref[keep]), marks), axis=1)]
    T = fit_rigid2d(ref[keep], dst)
    rms = float(np.sqrt(np.mean(np.sum((apply2d(T, ref[keep]) - dst) ** 2, axis=1))))
    info.update(support=[fids[k].id for k in keep], rms_mm=round(rms, 5))
    return T, info


def _distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(len(a), len(b)) distances between two sets of 2D points."""
    return np.hypot(a[:, None, 0] - b[None, :, 0], a[:, None, 1] - b[None, :, 1])


def global_body_pose(height, reliable, board, p, *, T_nominal: np.ndarray,
                     max_rotation_deg: float, max_offset_mm: float,
                     tol_mm: float = 0.08):
    """Placement of ``board`` from its bodies alone, wherever the board lies in the image.

    Every measured blob that has the size and shape of some component's body (above
    that body's presence threshold, not cut by the image border) is a candidate match
    of that body. Every two candidate matches of different bodies, at least
    :data:`MIN_PAIR_SPAN_MM` apart and as far apart in the image as on the board
    (within ``2 tol_mm``), propose a rigid placement; placements turned more than
    ``max_rotation_deg`` or moved more than ``max_offset_mm`` from ``T_nominal`` (with
    one body-search distance to spare) are dropped, as are pairs whose blobs' long axes
    do not turn with the placement. A placement's support is the number of bodies with
    a matching blob within ``tol_mm`` of where it puts them (each blob used once); the
    best-supported one (then the smallest summed residual) is refitted to its
    supporting bodies by least squares (2D Procrustes).

    Returns
    -------
    T : (3, 3) float64 or None
        None when no two bodies agree.
    info : dict
        ``support`` (body refs), ``rms_mm``, ``hypotheses`` (how many were scored).
    """
    comps = list(board.components)
    levels = sorted({round(presence_threshold_mm(c), 4) for c in comps})
    blobs_at = {lv: _measured_blobs(height, reliable, lv, p) for lv in levels}
    cand: list[tuple[int, _Blob, list]] = []   # (body, blob, the body's shapes it matches)
    for ci, c in enumerate(comps):
        for b in blobs_at[round(presence_threshold_mm(c), 4)]:
            shapes = _matched_shapes(c, b)
            if shapes:
                cand.append((ci, b, shapes))
    if len(cand) < 2:
        return None, {"reason": f"{len(cand)} body-sized blobs", "hypotheses": 0}
    src = np.array([[comps[ci].x_mm, comps[ci].y_mm] for ci, _, _ in cand])
    dst = np.array([b.xy for _, b, _ in cand])
    cidx = np.array([ci for ci, _, _ in cand])
    rot0 = math.degrees(math.atan2(T_nominal[1, 0], T_nominal[0, 0]))
    centre = np.array(board.size_mm, np.float64) / 2.0
    c_nom = apply2d(T_nominal, centre[None])[0]

    def support(T):
        pred = apply2d(T, src)
        r = np.hypot(*(pred - dst).T)
        ok = r <= tol_mm
        # Each body and each blob counted once: the nearest blob for each body.
        best: dict[int, tuple[float, int]] = {}
        for k in np.nonzero(ok)[0]:
            if cidx[k] not in best or r[k] < best[cidx[k]][0]:
                best[cidx[k]] = (float(r[k]), int(k))
        used_blobs = {}
        for ci, (rk, k) in best.items():
            key = dst[k].tobytes()
            if key not in used_blobs or rk < best[used_blobs[key]][0]:
                used_blobs[key] = ci
        keep = [best[ci][1] for ci in used_blobs.values()]
        return len(keep), -float(sum(r[k] for k in keep)), keep

    best = (0, 0.0, [])
    best_T = None
    n_hyp = 0
    scored: list[tuple[int, np.ndarray, list]] = []  # (support, placement, matches) of each
    for i in range(len(cand)):
        for j in range(i + 1, len(cand)):
            if cidx[i] == cidx[j] or cand[i][1] is cand[j][1]:
                continue
            d_b = float(np.hypot(*(src[i] - src[j])))
            if d_b < MIN_PAIR_SPAN_MM:
                continue
            if abs(float(np.hypot(*(dst[i] - dst[j]))) - d_b) > 2 * tol_mm:
                continue
            T = fit_rigid2d(src[[i, j]], dst[[i, j]])
            rot = math.degrees(math.atan2(T[1, 0], T[0, 0]))
            if _angle_diff(rot, rot0, 360.0) > max_rotation_deg + 1.0:
                continue
            if float(np.hypot(*(apply2d(T, centre[None])[0] - c_nom))) > max_offset_mm + BODY_SEARCH_MM:
                continue
            # The blobs' long axes must turn with the placement (square shapes say nothing).
            if all(_axis_turns_with(comps[cidx[k]], cand[k][1], rot, cand[k][2])
                   for k in (i, j)):
                n_hyp += 1
                s = support(T)
                scored.append((s[0], T, s[2]))
                if s[:2] > best[:2]:
                    best, best_T = s, T
    if best_T is None or best[0] < 2:
        return None, {"reason": "no two bodies agree", "hypotheses": n_hyp}
    def fit(idx) -> tuple[np.ndarray, float]:
        """Rigid placement of the matches ``idx`` and its RMS residual (mm)."""
        Ti = fit_rigid2d(src[idx], dst[idx])
        return Ti, float(np.sqrt(np.mean(np.sum((apply2d(Ti, src[idx]) - dst[idx]) ** 2, 1))))

    keep = best[2]
    T, rms = fit(keep)
    # The best support of a rival placement: one that pairs a body of the best with
    # another blob (or a blob of the best with another body), or whose matches and the
    # best's together do not fit one placement within tol_mm RMS. A layout with
    # repeated parts offers a second placement nearly as well supported, a generic one
    # none. Two-body fits of the same matches are the same answer, however far apart
    # they put the board's corners (test seed demo 10087: C1 + C2, C1 + R2 and R2 + C2,
    # centroids 28-85 µm off, turned -3.8°, -4.9° and -4.1°; all three fit one
    # placement at 48-50 µm RMS).
    mine = {int(cidx[k]): dst[k].tobytes() for k in keep}
    mine_blobs = {v: c for c, v in mine.items()}

    def rivals(matches) -> bool:
        pairs = {int(cidx[k]): dst[k].tobytes() for k in matches}
        if any(mine.get(c, b) != b or mine_blobs.get(b, c) != c for c, b in pairs.items()):
            return True
        return fit(sorted(set(keep) | set(matches)))[1] > tol_mm

    rival = max((n for n, _, matches in scored if rivals(matches)), default=0)
    return T, {"support": sorted(comps[cidx[k]].ref for k in keep), "hypotheses": n_hyp,
               "rival_support": int(rival),
               "rms_mm": round(rms, 5)}
