"""Find the reference board in the measured height map: coarse search, then ICP.

Coarse
    The reference heights (bodies, leads, nominal fillets; :mod:`._reference`) are
    rasterised at a coarse pixel size for every candidate rotation in
    ``±max_rotation_deg`` and matched to the measured heights (above the board plane,
    reliable pixels only) by masked normalised cross-correlation computed with FFTs
    for every translation within ``±max_offset_mm``. The best (rotation, translation)
    is refined at twice the resolution around it, with sub-pixel / sub-step peak
    interpolation.
Body layout
    The measured body blobs (size and shape of a reference body, above its presence
    threshold) are matched to the reference layout, every two matches proposing a rigid
    placement (:func:`~._features.global_body_pose`). The correlation can prefer a wrong
    pose when a large part of the reference is absent or changed (the largest part
    missing, tombstoned, shifted or cut by the field edge); after both placements are
    refined by the local features, the one under which more bodies and fiducials lie
    where it puts them is kept.
Fine
    Open3D point-to-plane ICP of the measured reliable points against points sampled on
    the reference mesh (trimesh). Only the in-plane part of the ICP's motion (rotation
    about z and x, y translation) is kept: heights come from the board-plane fit. The
    ICP result is used only when it stays near the coarse one and does not make the fit
    worse.
Decision
    The board counts as located when the correlation score, the fitness (fraction of
    the measured raised points — bodies, leads, solder — that lie within
    ``icp_distance_mm`` of the reference surface) and the inlier RMSE pass the limits of
    :class:`InspectConfig`, or when the features vouch for it (most bodies, or two
    fiducials, agree with it to half the consensus distance and the fitness passes)
    although a large part missing lowers the correlation and the reference coverage.
    Otherwise ``converged`` is False and ``reason`` says why;
    :func:`smdinspect.inspect.inspect_surface` then raises
    :class:`~smdinspect.errors.BoardNotLocatedError` instead of judging joints against a
    wrong alignment.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import InputError
from ._config import InspectConfig
from ._geometry import apply2d, decompose2d, polygon_mask, rigid2d, world_to_pixel
from ._features import (
    BODY_SEARCH_MM,
    CONSENSUS_MM,
    feature_pairs,
    global_body_pose,
    global_fiducial_pose,
    refine_with_features,
    residuals,
)
from ._reference import Prism, reference_points, reference_prisms, render_reference

__all__ = ["RegistrationResult", "masked_ncc", "register_board"]

log = logging.getLogger(__name__)

#: Measured points standing higher than this above the board count as "raised".
RAISED_MM = 0.08


@dataclass(frozen=True)
class RegistrationResult:
    """Where the board lies in the measurement.

    Attributes
    ----------
    transform : (3, 3) float64
        Placement ``WORLD = transform · BOARD`` (homogeneous 2D rigid transform, mm).
    fitness : float
        The smaller of two fractions: of the measured raised reliable points (higher
        than 0.08 mm above the board, inside the board outline) that lie within
        ``icp_distance_mm`` of the reference surface, and of the reference's raised top
        surface points (over reliable pixels of the image) that the measurement
        reproduces within ``icp_distance_mm``. Both are near 1 for the right board.
    rmse_mm : float
        RMS distance of those inliers to the reference surface.
    converged : bool
        True when the board was located (every check passed).
    method : str
        The stages whose result was kept: ``"coarse"``, ``"coarse+features"``, with
        ``"+icp"`` when the ICP ran and improved the fit (see ``meta``).
    reason : str
        Why the board was not located ("" when it was).
    score : float
        Best masked normalised cross-correlation of the height maps (−1..1).
    offset_mm : (float, float)
        Where the board centre landed relative to the image centre, WORLD frame.
    meta : dict
        Details (timings, coarse and ICP candidates).
    """

    transform: np.ndarray
    fitness: float
    rmse_mm: float
    converged: bool
    method: str
    reason: str = ""
    score: float = float("nan")
    offset_mm: tuple[float, float] = (float("nan"), float("nan"))
    meta: dict[str, Any] = field(default_factory=dict, repr=False)

    @property
    def rotation_deg(self) -> float:
        return decompose2d(self.transform)[0]

    @property
    def translation_mm(self) -> tuple[float, float]:
        _, tx, ty = decompose2d(self.transform)
        return tx, ty

    def to_dict(self) -> dict[str, Any]:
        return {
            "method": self.method,
            "converged": bool(self.converged),
            "reason": self.reason,
            "transform": np.round(self.transform, 9).tolist(),
            "rotation_deg": round(self.rotation_deg, 4),
            "translation_mm": [round(v, 5) for v in self.translation_mm],
            "offset_mm": [round(float(v), 5) if math.isfinite(v) else None for v in self.offset_mm],
            "score": _finite(self.score, 4),
            "fitness": _finite(self.fitness, 4),
            "rmse_mm": _finite(self.rmse_mm, 5),
        }


def _finite(v: float, nd: int):
    return round(float(v), nd) if math.isfinite(float(v)) else None


# --------------------------------------------------------------------------------------
# Masked normalised cross-correlation.
# --------------------------------------------------------------------------------------


class _Fixed:
    """FFTs of the fixed image for repeated masked NCC against moving images."""

    def __init__(self, fixed: np.ndarray, mask: np.ndarray, moving_shape: tuple[int, int]):
        from scipy import fft as sfft

        self.sfft = sfft
        f = np.where(mask, fixed, 0.0).astype(np.float64)
        m = mask.astype(np.float64)
        self.hf, self.wf = f.shape
        self.hm, self.wm = moving_shape
        self.out = (self.hf + self.hm - 1, self.wf + self.wm - 1)
        self.fft_shape = (sfft.next_fast_len(self.out[0], real=True),
                          sfft.next_fast_len(self.out[1], real=True))
        # C[u] = Σ_r a[r] b[r + u − (hf − 1)]: convolve the flipped fixed terms.
        self.Fm = self._f(m[::-1, ::-1])
        self.Ff = self._f(f[::-1, ::-1])
        self.Fff = self._f((f * f)[::-1, ::-1])
        self.scale = max(1.0, float(np.max(np.abs(f)))) ** 2

    def _f(self, a: np.ndarray) -> np.ndarray:
        return self.sfft.rfft2(a, self.fft_shape)

    def _c(self, A: np.ndarray, B: np.ndarray) -> np.ndarray:
        return self.sfft.irfft2(A * B, self.fft_shape)[: self.out[0], : self.out[1]]

    def ncc(self, moving: np.ndarray, mask: np.ndarray, min_overlap: float) -> tuple[np.ndarray, np.ndarray]:
        g = np.where(mask, moving, 0.0).astype(np.float64)
        m = mask.astype(np.float64)
        Gm, Gg, Ggg = self._f(m), self._f(g), self._f(g * g)
        n = np.round(self._c(self.Fm, Gm))
        sf, sg = self._c(self.Ff, Gm), self._c(self.Fm, Gg)
        sfg = self._c(self.Ff, Gg)
        sff, sgg = self._c(self.Fff, Gm), self._c(self.Fm, Ggg)
        with np.errstate(divide="ignore", invalid="ignore"):
            num = sfg - sf * sg / n
            vf = sff - sf * sf / n
            vg = sgg - sg * sg / n
            out = num / np.sqrt(np.clip(vf, 0, None) * np.clip(vg, 0, None))
        eps = 1e-9 * self.scale * max(1.0, float(n.max()))
        ok = (n >= max(min_overlap, 2.0)) & (vf > eps) & (vg > eps)
        return np.where(ok, np.clip(out, -1.0, 1.0), -1.0), n


def masked_ncc(fixed, fixed_mask, moving, moving_mask, *, min_overlap: float = 1.0):
    """Masked normalised cross-correlation for every integer shift (Padfield 2012).

    Only pixels where both masks are set enter the correlation at each shift.

    Parameters
    ----------
    fixed : (Hf, Wf) float
    fixed_mask : (Hf, Wf) bool
    moving : (Hm, Wm) float
    moving_mask : (Hm, Wm) bool
    min_overlap : float
        Shifts with fewer overlapping pixels get −1.

    Returns
    -------
    ncc : (Hf + Hm − 1, Wf + Wm − 1) float64
        Element ``[u, v]`` compares ``fixed[r, c]`` with
        ``moving[r + u − (Hf − 1), c + v − (Wf − 1)]``.
    overlap : same shape, float64
        Number of overlapping pixels.
    """
    fixed = np.asarray(fixed, np.float64)
    moving = np.asarray(moving, np.float64)
    if fixed.ndim != 2 or moving.ndim != 2:
        raise InputError(f"fixed and moving must be 2D; got {fixed.shape} and {moving.shape}")
    if fixed_mask.shape != fixed.shape or moving_mask.shape != moving.shape:
        raise InputError("masks must have the shapes of their images")
    return _Fixed(fixed, np.asarray(fixed_mask, bool), moving.shape).ncc(
        moving, np.asarray(moving_mask, bool), min_overlap)


def _parabola_peak(a: float, b: float, c: float) -> tuple[float, float]:
    """Vertex (offset in [−0.5, 0.5], value) of the parabola through (−1, a), (0, b), (1, c)."""
    den = a - 2.0 * b + c
    if den >= 0 or not np.isfinite(den):
        return 0.0, float(b)
    off = float(np.clip(0.5 * (a - c) / den, -0.5, 0.5))
    return off, float(b - 0.125 * (a - c) ** 2 / den) if abs(off) < 0.5 else float(b)


# --------------------------------------------------------------------------------------
# Coarse search.
# --------------------------------------------------------------------------------------


def _block_mean(height: np.ndarray, mask: np.ndarray, k: int):
    """Mean of reliable pixels over k×k blocks; a block is valid when half its pixels are."""
    h, w = height.shape
    hq, wq = h // k, w // k
    hv = np.where(mask, height, 0.0)[: hq * k, : wq * k].reshape(hq, k, wq, k).sum(axis=(1, 3))
    n = mask[: hq * k, : wq * k].reshape(hq, k, wq, k).sum(axis=(1, 3))
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(n > 0, hv / np.maximum(n, 1), 0.0)
    return mean, n >= 0.5 * k * k


@dataclass
class _Level:
    fixed: np.ndarray
    fmask: np.ndarray
    k: int                      # block size in native pixels
    p: float                    # native pixel size (mm)
    q: float                    # block size in mm
    origin: tuple[float, float]  # world position of block (Hq−1, 0)


def _level(height: np.ndarray, reliable: np.ndarray, p: float, k: int, clip: tuple[float, float]) -> _Level:
    h = height.shape[0]
    mean, valid = _block_mean(np.clip(height, *clip), reliable, k)
    hq = mean.shape[0]
    # Block (i, j) centre: native row i·k + (k−1)/2, col j·k + (k−1)/2.
    x0 = (k - 1) / 2.0 * p
    y0 = (h - 1 - ((hq - 1) * k + (k - 1) / 2.0)) * p
    return _Level(mean, valid, k, p, k * p, (x0, y0))


def _render_level(level: _Level, prisms, board, T, shape, origin, clip):
    """The reference rendered at the native pixel size, then block-averaged like the
    measurement (so both carry the same partial-pixel edges)."""
    k = level.k
    nat_origin = (origin[0] - (k - 1) / 2.0 * level.p, origin[1] - (k - 1) / 2.0 * level.p)
    mov, mmask = render_reference(prisms, T, shape=(shape[0] * k, shape[1] * k),
                                  pixel_size_mm=level.p, origin_mm=nat_origin, board=board)
    if k == 1:
        return np.clip(mov, *clip), mmask
    return _block_mean(np.clip(mov, *clip), mmask, k)


def _search(level: _Level, prisms: list[Prism], board, T0: np.ndarray, pivot: np.ndarray,
            angles: np.ndarray, margin_mm: float, min_overlap: int, clip):
    """Best (score, T) over ``angles`` (rotation about world point ``pivot`` applied after
    ``T0``) and every translation within ``±margin_mm``.

    Each angle's score is the interpolated (parabolic) peak of the correlation, so the
    scores of neighbouring angles compare fairly whatever the sub-block phase."""
    m = int(math.ceil(margin_mm / level.q))
    hf, wf = level.fixed.shape
    shape = (hf + 2 * m, wf + 2 * m)
    origin = (level.origin[0] - m * level.q, level.origin[1] - m * level.q)
    fx = _Fixed(level.fixed, level.fmask, shape)
    scores = []
    cands = []
    for a in angles:
        Ta = _about(pivot, a) @ T0
        mov, mmask = _render_level(level, prisms, board, Ta, shape, origin, clip)
        ncc, _ = fx.ncc(mov, mmask, min_overlap)
        # Keep shifts within ±m blocks: u − (hf − 1) ∈ [0, 2m].
        win = ncc[hf - 1: hf + 2 * m, wf - 1: wf + 2 * m]
        i, j = np.unravel_index(int(np.argmax(win)), win.shape)
        s = float(win[i, j])
        di, si = _parabola_peak(win[i - 1, j], s, win[i + 1, j]) if 0 < i < win.shape[0] - 1 else (0.0, s)
        dj, sj = _parabola_peak(win[i, j - 1], s, win[i, j + 1]) if 0 < j < win.shape[1] - 1 else (0.0, s)
        peak = s + (si - s) + (sj - s) if s > -1 else s
        # moving[r + i] meets fixed[r]: the reference must move by (m − i) blocks (rows).
        d_row, d_col = m - (i + di), m - (j + dj)
        scores.append(peak)
        cands.append((a, d_col * level.q, -d_row * level.q))
    scores = np.array(scores)
    kbest = int(np.argmax(scores))
    if scores[kbest] <= -1:
        return -1.0, T0, scores
    a, dx, dy = cands[kbest]
    da = 0.0
    if 0 < kbest < len(angles) - 1:
        step = float(angles[1] - angles[0])
        da = _parabola_peak(scores[kbest - 1], scores[kbest], scores[kbest + 1])[0] * step
    T = rigid2d(0.0, dx, dy) @ _about(pivot, a) @ T0
    if da:
        # The translation found at angle a stays right to first order; rotate about the
        # board centre (pivot moved with the translation) by the sub-step residue.
        T = _about(pivot + np.array([dx, dy]), da) @ T
    return float(scores[kbest]), T, scores


def _about(pivot: np.ndarray, angle_deg: float) -> np.ndarray:
    return rigid2d(0.0, pivot[0], pivot[1]) @ rigid2d(angle_deg, 0.0, 0.0) @ rigid2d(0.0, -pivot[0], -pivot[1])


# --------------------------------------------------------------------------------------
# The registration.
# --------------------------------------------------------------------------------------


def register_board(
    height_mm: np.ndarray,
    reliable: np.ndarray,
    board,
    *,
    pixel_size_mm: float,
    config: InspectConfig | None = None,
    initial: np.ndarray | None = None,
    aif: np.ndarray | None = None,
) -> RegistrationResult:
    """Locate ``board`` in a measured height map.

    Parameters
    ----------
    height_mm : (H, W) float
        Heights above the board plane (mm), WORLD frame of :class:`~smdinspect.sff.Surface`.
    reliable : (H, W) bool
        Pixels whose height can be trusted.
    board : Board
    pixel_size_mm : float
    config : InspectConfig, optional
    initial : (3, 3) float64, optional
        Skip the coarse search and start the fine registration from this placement.
    aif : (H, W) or (H, W, 3) array, optional
        All-in-focus image; fiducials are located in it for the fine registration.

    Returns
    -------
    RegistrationResult
        ``converged`` False (with ``reason``) when the board was not found; never raises
        for a poor match.
    """
    cfg = config or InspectConfig()
    height = np.asarray(height_mm, np.float64)
    reliable = np.asarray(reliable, bool)
    if height.ndim != 2 or reliable.shape != height.shape:
        raise InputError(f"height_mm and reliable must be (H, W) of one shape; got "
                         f"{height.shape} and {reliable.shape}")
    if not (pixel_size_mm and pixel_size_mm > 0):
        raise InputError(f"pixel_size_mm must be > 0 to locate the board; got {pixel_size_mm!r}")
    p = float(pixel_size_mm)
    reliable = reliable & np.isfinite(height)
    t_start = time.perf_counter()
    meta: dict[str, Any] = {}
    prisms = reference_prisms(board, fillets=True)
    top = max(pr.max_top_mm for pr in prisms)
    clip = (-0.1, top + 0.1)
    H, W = height.shape
    centre_img = np.array([(W - 1) * p / 2.0, (H - 1) * p / 2.0])
    centre_board = np.array(board.size_mm, np.float64) / 2.0
    board_area_mm2 = board.size_mm[0] * board.size_mm[1]

    if initial is None:
        T0 = rigid2d(0.0, *(centre_img - centre_board))
        # Level 1: every rotation and translation at the coarse pixel size; then halve
        # the block size (down to ~0.04 mm or the native pixel), searching ±2 quarter
        # steps of the previous angle step and a few blocks of translation around the
        # best so far.
        k = max(1, int(round(cfg.coarse_pixel_size_mm / p)))
        step = 1.0
        n_ang = int(math.ceil(cfg.max_rotation_deg / step))
        angles = np.arange(-n_ang, n_ang + 1) * step
        T, pivot, margin = T0, centre_img, cfg.max_offset_mm
        score = -1.0  # stays -1 when the first level finds nothing
        levels = []
        while True:
            lv = _level(height, reliable, p, k, clip)
            min_ov = int(0.25 * board_area_mm2 / lv.q ** 2)
            s_k, T_k, sc = _search(lv, prisms, board, T, pivot, angles, margin, min_ov, clip)
            levels.append({"pixel_mm": lv.q, "score": round(s_k, 5),
                           "rotation_deg": round(decompose2d(T_k)[0], 4),
                           "angle_scores": np.round(sc, 4).tolist()})
            if s_k <= -1:
                break
            score, T = s_k, T_k
            # Stop at ~0.04 mm: the feature fit takes it from there.
            if k == 1 or lv.q <= 0.045:
                break
            margin = 3 * lv.q
            k = max(1, k // 2)
            step /= 4.0
            angles = np.arange(-2, 3) * step
            pivot = apply2d(T, centre_board[None])[0]
        meta["coarse"] = {"levels": levels, "seconds": round(time.perf_counter() - t_start, 3)}
        meta["coarse_transform"] = T.copy()
        log.debug("coarse registration: score %.3f, rotation %.3f deg", score, decompose2d(T)[0])
    else:
        T = np.asarray(initial, np.float64)
        if T.shape != (3, 3):
            raise InputError(f"initial must be a (3, 3) matrix; got shape {T.shape}")
        score = float("nan")

    # Fine: body centroids and fiducials (robust rigid fit), then optionally ICP.
    method = "coarse"
    if cfg.fine_features:
        pairs = feature_pairs(height, reliable, aif, board, T, p)
        T_feat, feat_info = refine_with_features(pairs, T)
        meta["features"] = feat_info
        if T_feat is not None and _moved_mm(T, T_feat, board) > 0.05:
            # A large correction (the coarse match locked onto one shifted part): find
            # the features again where they now should be, fiducials included.
            pairs2 = feature_pairs(height, reliable, aif, board, T_feat, p)
            T_feat2, info2 = refine_with_features(pairs2, T_feat)
            if T_feat2 is not None:
                T_feat, feat_info = T_feat2, info2
                meta["features"] = feat_info
        if T_feat is not None:
            moved = _moved_mm(T, T_feat, board)
            feat_info["moved_mm"] = round(moved, 5)
            if moved <= 0.25:
                T, method = T_feat, "coarse+features"
            elif moved <= 1.0:
                # Keep a large correction only when the measurement agrees better.
                ref_pts0, _ = reference_points(board, spacing_mm=max(p, 0.04), seed=cfg.seed)
                meas0 = _measured_points(height, reliable, p, board, T, max_points=20000,
                                         seed=cfg.seed)
                f_c, _ = _evaluate(meas0, ref_pts0, T, cfg.icp_distance_mm)
                f_f, _ = _evaluate(meas0, ref_pts0, T_feat, cfg.icp_distance_mm)
                feat_info["fitness_coarse_vs_features"] = [round(f_c, 4), round(f_f, 4)]
                used = feat_info.get("used", [])
                n_fid = sum(u.startswith("fiducial:") for u in used)
                n_rej = len(feat_info.get("rejected", []))
                # Fiducials that agree are the board's own reference marks; without
                # them, most bodies must agree (one large shifted part pulls the
                # height-map fitness its way).
                if f_f > f_c or n_fid >= 2 or (len(used) >= 3 and len(used) >= 2 * n_rej):
                    T, method = T_feat, "coarse+features"
                else:
                    feat_info["rejected_fit"] = (f"moved the board by {moved:.3f} mm without "
                                                 f"a better fitness")
            else:
                feat_info["rejected_fit"] = f"moved the board by {moved:.3f} mm"
    if cfg.fine_features and initial is None:
        T, method = _prefer_body_layout(height, reliable, aif, board, p, cfg, T, method,
                                        centre_img - centre_board, meta)
        T, method = _prefer_fiducial_layout(height, reliable, aif, board, p, cfg, T, method,
                                            centre_img - centre_board, meta)
    ref_pts, ref_n = reference_points(board, spacing_mm=max(p, 0.04), seed=cfg.seed)
    meas = _measured_points(height, reliable, p, board, T, max_points=20000, seed=cfg.seed)
    fit0, rmse0 = _evaluate(meas, ref_pts, T, cfg.icp_distance_mm)
    T_final, fit, rmse = T, fit0, rmse0
    icp_meta: dict[str, Any] = {"fitness_before": fit0, "rmse_mm_before": rmse0}
    if cfg.icp and len(meas) >= 100 and fit0 > 0.05:
        T_icp = _icp(meas, ref_pts, ref_n, T, cfg.icp_distance_mm)
        da, dx, dy = decompose2d(np.linalg.inv(T) @ T_icp)
        moved = _moved_mm(T, T_icp, board)
        fit1, rmse1 = _evaluate(meas, ref_pts, T_icp, cfg.icp_distance_mm)
        icp_meta.update({"icp_fitness": fit1, "icp_rmse_mm": rmse1, "icp_moved_mm": moved,
                         "icp_rotated_deg": da})
        if abs(da) <= 1.0 and moved <= 0.25 and fit1 > fit0 and rmse1 <= rmse0:
            method, T_final, fit, rmse = method + "+icp", T_icp, fit1, rmse1
        else:
            icp_meta["rejected"] = (f"ICP moved {moved:.3f} mm / {da:.2f} deg, fitness "
                                    f"{fit0:.3f} -> {fit1:.3f}, rmse {rmse0:.4f} -> {rmse1:.4f}")
    meta["icp"] = icp_meta
    coverage = _coverage(height, reliable, p, ref_pts, ref_n, T_final, cfg.icp_distance_mm)
    meta["forward_fitness"] = fit
    meta["reference_coverage"] = coverage
    # Most parts found where the placement puts them (RMS within the consensus
    # distance: shape-from-focus body centroids carry 10-60 µm of bias, the most
    # through an ordinary lens) and the measured raised points lie on the reference:
    # the board is located even when a large part is missing (it takes most of the
    # reference's raised area, so the correlation and the reference coverage drop; the
    # joints then say what is missing).
    feat = meta.get("features") or {}
    used_bodies = [u for u in feat.get("used", []) if u.startswith("body:")]
    used_fids = [u for u in feat.get("used", []) if u.startswith("fiducial:")]
    # Fiducials are the board's own reference marks: two or more that agree with the
    # placement (with at least three features in all, so the fit has redundancy)
    # locate the board however many parts are defective.
    # "Most bodies" of those the measured field shows: a field that cuts the board leaves
    # the parts beyond its edge nothing to vouch with.
    in_view = _components_in_view(board, T_final, height_mm.shape, p)
    meta["components_in_view"] = in_view
    agreed = ("features" in method and len(feat.get("used", [])) >= 3
              and float(feat.get("rms_mm", 1.0)) <= CONSENSUS_MM)
    # With fiducials the measured raised points need not lie on the reference: what
    # stands off it (a tombstone, a bulging fillet, a part where none belongs) is for
    # the verdicts to name (test seed demo 10064: three fiducials agreed within 2 µm,
    # the missing SOIC-8, a 1206 stood at 50° and an excess fillet left 58 % of the
    # raised points on the reference, and the board was not located).
    by_fiducials = agreed and len(used_fids) >= 2
    meta["located_by_fiducials"] = bool(by_fiducials)
    by_features = by_fiducials or (agreed and len(used_bodies) >= 0.5 * in_view
                                   and fit >= cfg.min_fitness)
    # Or the bodies' layout alone, when it is unambiguous: at least two bodies agree with
    # the placement, no placement elsewhere is as well supported, and the measured raised
    # points lie on the reference. A board whose parts are mostly missing, shifted or
    # tombstoned leaves a minority of bodies to vouch, and a large missing part takes
    # most of the reference coverage with it: the pose is still the one the layout
    # allows. (A layout of repeated parts offers a rival placement nearly as well
    # supported; then the majority rule above decides.)
    layout = meta.get("body_layout") or {}
    n_layout = len(layout.get("support", []))
    by_layout = (bool(layout.get("agrees")) and n_layout >= 2
                 and int(layout.get("rival_support", n_layout)) < n_layout
                 and float(layout.get("rms_mm", 1.0)) <= CONSENSUS_MM and fit >= cfg.min_fitness)
    meta["located_by_layout"] = bool(by_layout)
    by_features = by_features or by_layout
    meta["located_by_features"] = bool(by_features)
    if math.isfinite(coverage) and not by_features:
        fit = min(fit, coverage)
    meta["seconds"] = round(time.perf_counter() - t_start, 3)

    reasons = []
    if math.isfinite(score) and score < cfg.min_match_score and not by_features:
        reasons.append(f"height maps correlate poorly with the reference (score {score:.2f} < "
                       f"{cfg.min_match_score})")
    if len(meas) < 100:
        reasons.append(f"only {len(meas)} reliable raised points over the board")
    if not (fit >= cfg.min_fitness) and not by_fiducials:
        reasons.append(f"fitness {fit:.2f} < {cfg.min_fitness} (measured parts do not lie on "
                       f"the reference surface)")
    if not math.isfinite(rmse):
        reasons.append(f"no measured point lies within {cfg.icp_distance_mm * 1000:.0f} µm of "
                       "the reference surface (no inlier RMSE)")
    elif rmse > cfg.max_rmse_mm:
        reasons.append(f"inlier RMSE {rmse * 1000:.1f} µm > {cfg.max_rmse_mm * 1000:.0f} µm")
    offset = apply2d(T_final, centre_board[None])[0] - centre_img
    result = RegistrationResult(
        transform=T_final, fitness=float(fit), rmse_mm=float(rmse), converged=not reasons,
        method=method, reason="; ".join(reasons), score=float(score),
        offset_mm=(float(offset[0]), float(offset[1])), meta=meta)
    log.info("registration %s: rotation %.3f deg, offset (%.3f, %.3f) mm, score %.3f, "
             "fitness %.3f, rmse %.1f µm%s", method, result.rotation_deg, *result.offset_mm,
             score, fit, rmse * 1000, "" if not reasons else " -- NOT LOCATED: " + result.reason)
    return result


def _support(pairs, T) -> tuple[int, list[str]]:
    """Features found where ``T`` puts them (within the consensus distance)."""
    ok = [f"{fp.kind}:{fp.id}" for fp, res in zip(pairs, residuals(pairs, T))
          if res <= CONSENSUS_MM]
    return len(ok), ok


def _prefer_body_layout(height, reliable, aif, board, p, cfg, T, method, t_nominal, meta):
    """Check the placement against one found from the bodies' layout alone.

    The height-map correlation can prefer a wrong pose when a large part of the
    reference is absent or changed (a missing or tombstoned part, a part cut by the
    field edge): its optimum then follows the remaining large shapes. Matching the
    measured body blobs to the reference layout (:func:`global_body_pose`) gives an
    independent placement (see :func:`_prefer`). A board without two matching bodies
    keeps the correlation's placement. Two bodies alone fit any placement exactly: one
    of them biased (an excess fillet over its end) turns the board with it.
    """
    T_b, info = global_body_pose(height, reliable, board, p, T_nominal=rigid2d(0.0, *t_nominal),
                                 max_rotation_deg=cfg.max_rotation_deg,
                                 max_offset_mm=cfg.max_offset_mm)
    meta["body_layout"] = info
    if T_b is None:
        return T, method
    return _prefer(height, reliable, aif, board, p, cfg, T, method, T_b, "bodies", info, meta)


def _prefer_fiducial_layout(height, reliable, aif, board, p, cfg, T, method, t_nominal, meta):
    """Check the placement against one found from the fiducials alone
    (:func:`global_fiducial_pose`, see :func:`_prefer`).

    When the largest part is missing and the others are shifted, tombstoned or cut by
    the field edge, neither the correlation nor the bodies' layout may find the board,
    and the fiducials are then searched where a wrong placement puts them (tuning seed
    demo 239: U1 missing, C2 shifted, R3 tombstoned, C1 and R2 cut, two fiducials in
    view: not located)."""
    T_f, info = global_fiducial_pose(aif, board, p, T_nominal=rigid2d(0.0, *t_nominal),
                                     max_rotation_deg=cfg.max_rotation_deg,
                                     max_offset_mm=cfg.max_offset_mm)
    meta["fiducial_layout"] = info
    if T_f is None:
        return T, method
    return _prefer(height, reliable, aif, board, p, cfg, T, method, T_f, "fiducials", info,
                   meta)


def _prefer(height, reliable, aif, board, p, cfg, T, method, T_b, name, info, meta):
    """The placement ``T`` or the independent one ``T_b`` (found from ``name``): each is
    refined by the local features, and the one under which more bodies and fiducials lie
    where it puts them wins (ties: the better fitness of the measured raised points)."""
    if _moved_mm(T, T_b, board) <= CONSENSUS_MM:
        info["agrees"] = True
        return T, method
    method_b = name
    pairs_b = feature_pairs(height, reliable, aif, board, T_b, p)
    T_bf, info_b = refine_with_features(pairs_b, T_b)
    if T_bf is not None and _moved_mm(T_b, T_bf, board) <= BODY_SEARCH_MM:
        T_b, method_b = T_bf, f"{name}+features"
        # the features again where the refined placement puts them (a fiducial missed
        # from the layout's placement is found now), and the fit on all of them
        pairs_b = feature_pairs(height, reliable, aif, board, T_b, p)
        T_bf, info_bf = refine_with_features(pairs_b, T_b)
        if T_bf is not None and _moved_mm(T_b, T_bf, board) <= CONSENSUS_MM:
            T_b, info_b = T_bf, info_bf
            pairs_b = feature_pairs(height, reliable, aif, board, T_b, p)
    pairs_a = feature_pairs(height, reliable, aif, board, T, p)
    n_a, ok_a = _support(pairs_a, T)
    n_b, ok_b = _support(pairs_b, T_b)
    info["support_current_vs_layout"] = [n_a, n_b]
    if n_b < n_a or n_b == 0:
        return T, method
    ref_pts, _ = reference_points(board, spacing_mm=max(p, 0.04), seed=cfg.seed)
    meas = _measured_points(height, reliable, p, board, T, max_points=20000, seed=cfg.seed)
    meas_b = _measured_points(height, reliable, p, board, T_b, max_points=20000, seed=cfg.seed)
    f_a = _evaluate(meas, ref_pts, T, cfg.icp_distance_mm)[0]
    f_b = _evaluate(meas_b, ref_pts, T_b, cfg.icp_distance_mm)[0]
    info["fitness_current_vs_layout"] = [round(f_a, 4), round(f_b, 4)]
    # More features agreeing wins; on a tie the measured raised points decide. (The
    # fitness alone cannot: a large shifted part pulls it towards its own placement.)
    better = f_b > f_a if n_b == n_a else True
    if not better:
        return T, method
    info["kept"] = info["agrees"] = True
    if method_b.endswith("+features"):
        meta["features"] = info_b
    else:
        meta["features"] = {"used": ok_b, "rejected": [], "rms_mm": info.get("rms_mm")}
    log.debug("placement from the %s layout (%d features agree) replaces %s (%d)",
              name, n_b, method, n_a)
    return T_b, method_b


def _moved_mm(T0: np.ndarray, T1: np.ndarray, board) -> float:
    """Largest displacement of the board's corners between two placements (mm)."""
    c = board.outline_mm()
    return float(np.max(np.hypot(*(apply2d(T1, c) - apply2d(T0, c)).T)))


def _measured_points(height, reliable, p, board, T, *, max_points, seed):
    """Reliable raised points (WORLD frame) inside the board outline under ``T``."""
    H, W = height.shape
    outline = apply2d(T, board.outline_mm())
    inside = polygon_mask(world_to_pixel(outline, shape=(H, W), pixel_size_mm=p), (H, W))
    sel = reliable & inside & (height > RAISED_MM)
    rows, cols = np.nonzero(sel)
    if len(rows) > max_points:
        idx = np.random.default_rng(seed).choice(len(rows), max_points, replace=False)
        rows, cols = rows[idx], cols[idx]
    return np.column_stack([cols * p, (H - 1 - rows) * p, height[rows, cols]])


def _components_in_view(board, T: np.ndarray, shape: tuple[int, int], p: float) -> int:
    """How many components' bodies lie wholly inside the image under placement ``T``."""
    H, W = shape
    n = 0
    for comp in board.components:
        cr = world_to_pixel(apply2d(T, np.asarray(comp.body_polygon_mm(), float)),
                            shape=(H, W), pixel_size_mm=p)
        n += bool(np.all((cr[:, 0] >= 0) & (cr[:, 0] <= W - 1)
                         & (cr[:, 1] >= 0) & (cr[:, 1] <= H - 1)))
    return n


def _to_world3(ref_pts: np.ndarray, T: np.ndarray) -> np.ndarray:
    out = ref_pts.copy()
    out[:, :2] = apply2d(T, ref_pts[:, :2])
    return out


def _evaluate(meas: np.ndarray, ref_pts: np.ndarray, T: np.ndarray, dist: float):
    """(fitness, inlier rmse) of measured raised points against the reference placed by ``T``."""
    if len(meas) == 0:
        return 0.0, float("nan")
    from scipy.spatial import cKDTree

    tree = cKDTree(_to_world3(ref_pts, T))
    d, _ = tree.query(meas, k=1, distance_upper_bound=dist)
    inl = np.isfinite(d)
    if not inl.any():
        return 0.0, float("nan")
    return float(inl.mean()), float(np.sqrt(np.mean(d[inl] ** 2)))


def _coverage(height, reliable, p, ref_pts, ref_n, T, dist):
    """Fraction of the reference's raised top points (inside the image, over reliable
    pixels) that the measurement reproduces within ``dist`` (vertical + one pixel)."""
    H, W = height.shape
    sel = (ref_pts[:, 2] > RAISED_MM) & (ref_n[:, 2] > 0.5)
    pts = _to_world3(ref_pts[sel], T)
    cr = world_to_pixel(pts[:, :2], shape=(H, W), pixel_size_mm=p)
    c, r = np.round(cr[:, 0]).astype(int), np.round(cr[:, 1]).astype(int)
    inside = (c >= 1) & (c < W - 1) & (r >= 1) & (r < H - 1)
    c, r, z = c[inside], r[inside], pts[inside, 2]
    ok = reliable[r, c]
    if ok.sum() < 20:
        return float("nan")
    c, r, z = c[ok], r[ok], z[ok]
    best = np.full(len(z), np.inf)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            rel = reliable[r + dr, c + dc]
            dz = np.where(rel, np.abs(height[r + dr, c + dc] - z), np.inf)
            best = np.minimum(best, dz)
    return float(np.mean(best <= dist))


def _icp(meas, ref_pts, ref_n, T, dist):
    """Point-to-plane ICP (Open3D); returns the refined 2D placement."""
    try:
        import open3d as o3d
    except ImportError as exc:  # pragma: no cover - dependency of the package
        raise ImportError("the fine registration needs open3d: pip install open3d") from exc
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(meas))
    tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(_to_world3(ref_pts, T)))
    n = ref_n.copy()
    n[:, :2] = ref_n[:, :2] @ T[:2, :2].T
    tgt.normals = o3d.utility.Vector3dVector(n)
    res = o3d.pipelines.registration.registration_icp(
        src, tgt, float(dist), np.eye(4),
        o3d.pipelines.registration.TransformationEstimationPointToPlane(),
        o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=40))
    M = np.asarray(res.transformation)
    # reference_world ≈ M · measured  →  measured ≈ M⁻¹ · T · board; keep the in-plane part.
    yaw = math.degrees(math.atan2(M[1, 0], M[0, 0]))
    M2 = rigid2d(yaw, M[0, 3], M[1, 3])
    return np.linalg.inv(M2) @ T
