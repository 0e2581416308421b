"""``inspect_surface``: a measured Surface + a reference Board → verdict per joint."""

from __future__ import annotations

import logging
import time

import numpy as np

from ..errors import BoardNotLocatedError, InputError
from ..sff._surface import clipped_white
from ._config import InspectConfig
from ._features import position_covariance
from ._geometry import apply2d
from ._measure import (
    MeasureContext,
    chroma_map,
    fiducial_chroma,
    footprints,
    measure_board,
    pad_chroma_reference,
    pixel_uncertainty,
)
from ._plane import fit_board_plane
from ._register import RegistrationResult, register_board
from ._result import InspectionResult
from ._verdict import judge_component, judge_joint

__all__ = ["inspect_surface"]

log = logging.getLogger(__name__)


def _check_surface(surface) -> None:
    for name in ("height_mm", "reliable", "confidence", "aif", "pixel_size_mm"):
        if not hasattr(surface, name):
            raise InputError(f"surface must be a smdinspect.sff.Surface; it has no {name!r}")
    if surface.pixel_size_mm is None or not (float(surface.pixel_size_mm) > 0):
        raise InputError("the surface has no pixel size in mm; inspection needs one "
                         "(give --pixel-size-mm or set pixel_size_mm in stack.json)")
    h = np.asarray(surface.height_mm)
    if h.ndim != 2 or min(h.shape) < 16:
        raise InputError(f"surface height_mm must be (H, W) with H, W >= 16; got {h.shape}")
    if np.asarray(surface.reliable).shape != h.shape:
        raise InputError(f"surface reliable mask {np.asarray(surface.reliable).shape} does not "
                         f"match height_mm {h.shape}")


def inspect_surface(surface, board, config: InspectConfig | None = None, *,
                    initial_transform: np.ndarray | None = None) -> InspectionResult:
    """Locate ``board`` in ``surface``, measure and judge every joint.

    Parameters
    ----------
    surface : smdinspect.sff.Surface
        The measurement; needs ``pixel_size_mm``.
    board : Board
        The reference (see :func:`load_board`).
    config : InspectConfig, optional
    initial_transform : (3, 3) float64, optional
        Known placement WORLD = T · BOARD; skips the coarse search (ICP still runs).

    Returns
    -------
    InspectionResult

    Raises
    ------
    BoardNotLocatedError
        The board was not found with enough confidence (see
        :class:`RegistrationResult`); the error's ``registration`` attribute holds the
        details. Joints are never judged against a poor alignment.
    InputError
        The surface has no pixel size or bad shapes.
    """
    cfg = config or InspectConfig()
    if not isinstance(cfg, InspectConfig):
        raise InputError(f"config must be an InspectConfig; got {type(cfg).__name__}")
    _check_surface(surface)
    t0 = time.perf_counter()
    p = float(surface.pixel_size_mm)
    height, reliable, x, y = _grids(surface)
    if reliable.mean() < 0.05:
        raise BoardNotLocatedError(
            f"board not located: only {reliable.mean():.1%} of the surface is reliable; nothing to locate the "
            "board on (is the stack in focus range and textured?)")

    # 1. Global plane. The board is the lowest large surface, not necessarily the largest
    #    reliable one (a plain solder mask has little texture; an IC top has plenty), so
    #    RANSAC first sees only the lowest reliable points, then every point near that
    #    plane (a tilted board's far side), then the fit is repeated.
    plane0 = _board_plane(x, y, height, reliable, cfg)
    level0 = height - plane0.z_mm(x, y)

    # 2. Registration on the levelled heights.
    reg = register_board(level0, reliable, board, pixel_size_mm=p, config=cfg,
                         initial=initial_transform, aif=surface.aif)
    if not reg.converged:
        err = BoardNotLocatedError(f"board {board.name!r} not located: {reg.reason}")
        err.registration = reg  # type: ignore[attr-defined]
        raise err
    return _inspect_located(surface, board, reg, cfg, plane0=(plane0, level0), t0=t0,
                            grids=(height, reliable, x, y))


def _focus_window(surface) -> int:
    """The focus window (px) the surface was measured with (its ``meta`` config); 0 when
    none is recorded (true heights)."""
    config = (getattr(surface, "meta", None) or {}).get("config") or {}
    return int(config.get("window_px") or 0)


def _grids(surface):
    """Heights (float64), the reliable mask and the WORLD x, y of every pixel (mm)."""
    p = float(surface.pixel_size_mm)
    height = np.asarray(surface.height_mm, np.float64)
    reliable = np.asarray(surface.reliable, bool) & np.isfinite(height)
    H = height.shape[0]
    rows, cols = np.indices(height.shape)
    return height, reliable, cols * p, (H - 1 - rows) * p


def _inspect_located(surface, board, reg: RegistrationResult, cfg: InspectConfig, *,
                     plane0=None, t0: float | None = None, grids=None) -> InspectionResult:
    """Steps 3 and 4 of :func:`inspect_surface` on a board already located by ``reg``.

    ``plane0``: the first board plane and the heights levelled by it (fitted here when
    not given); ``t0``: the start
    time the result's ``seconds`` counts from; ``grids``: :func:`_grids` of the surface
    when already made. The tests call it with the scene's true placement to judge the
    verdict rules on a crop around one part, where registration (which needs the
    board's layout) has nothing to hold on to.
    """
    t0 = time.perf_counter() if t0 is None else t0
    p = float(surface.pixel_size_mm)
    height, reliable, x, y = _grids(surface) if grids is None else grids
    H, W = height.shape
    if plane0 is None:
        plane0 = _board_plane(x, y, height, reliable, cfg)
        plane0 = plane0, height - plane0.z_mm(x, y)
    plane0, level0 = plane0

    # 3. Refit the plane on the bare board only (outside every footprint).
    ctx = MeasureContext(height=level0, reliable=reliable, u_px=np.zeros_like(height),
                         bare=reliable, T=reg.transform, p=p, u_plane_mm=0.0)
    fps = footprints(board, ctx, margin_px=max(cfg.body_margin_mm, 0.1) / p)
    occupied = np.zeros(height.shape, bool)
    for m in fps.values():
        occupied |= m
    bare = reliable & ~occupied
    plane = plane0
    if bare.sum() >= 200:
        try:
            plane = fit_board_plane(np.column_stack([x[bare], y[bare], height[bare]]),
                                    distance_mm=cfg.plane_distance_mm, seed=cfg.seed)
        except Exception as exc:  # noqa: BLE001 - keep the first plane, say why
            log.warning("bare-board plane refit failed (%s); keeping the first plane", exc)
    level = (height - plane.z_mm(x, y)).astype(np.float64)
    u_plane = plane.rmse_mm / np.sqrt(max(plane.n_inliers, 1))
    step = float(np.median(np.diff(np.asarray(surface.z_mm, np.float64)))) \
        if np.size(getattr(surface, "z_mm", [])) >= 2 else float("nan")
    sigma = getattr(surface, "sigma_mm", None)
    u_px = (pixel_uncertainty(sigma, step, cfg.focus_noise) if sigma is not None
            else np.full(height.shape, np.nan))
    chroma = chroma_map(surface.aif)
    # The bare finish's colour: the fiducials', else the pads' own (a pad that shows
    # bare gold or copper), so no fiducial is needed to tell a bare pad from solder.
    # Grey fiducials say the finish is grey (HASL): then nothing on a pad that looks
    # coloured is the finish (a part's body seen over it, a reflection), and the cue
    # stays off.
    bare_chroma, fiducials_seen = fiducial_chroma(board, reg.transform, chroma, p)
    if not fiducials_seen:
        bare_chroma = pad_chroma_reference(board, reg.transform, chroma, p)
    field = getattr(surface, "field", None)
    field = None if field is None or np.asarray(field).shape != height.shape \
        else np.asarray(field, bool)
    ctx = MeasureContext(height=level, reliable=reliable, u_px=u_px,
                         bare=bare & (np.abs(level) <= 3 * cfg.plane_distance_mm),
                         T=reg.transform, p=p, u_plane_mm=float(u_plane), chroma=chroma,
                         bare_chroma=bare_chroma, field=field,
                         clipped=clipped_white(surface.aif), window_px=_focus_window(surface))

    # 4. Measure and judge.
    jm, cm = measure_board(board, ctx, cfg)
    feat = reg.meta.get("features") or {}
    fixed = feat.get("covariance")
    if fixed and "features" in reg.method and not feat.get("rejected_fit"):
        # how well the pairs the placement was fitted to fix it at each part (a
        # rotation poorly fixed by a compact cluster moves far parts most)
        for comp in board.components:
            cm[comp.ref].offset_cov_mm2 = position_covariance(
                fixed["cov"], fixed["centre"], reg.transform, (comp.x_mm, comp.y_mm))
    comps = []
    joints = []
    for comp in board.components:
        cr = judge_component(comp, cm[comp.ref], cfg)
        comps.append(cr)
        for j in comp.joints:
            joints.append(judge_joint(j, comp, jm[j.id], cr, cfg,
                                      component_in_field=cm[comp.ref].in_field_fraction))
    seconds = round(time.perf_counter() - t0, 3)
    from ..calibrate import applied_calibration

    result = InspectionResult(
        board=board.name, board_source=str(getattr(board, "source", "")), registration=reg,
        plane=plane, joints=joints, components=comps, config=cfg, pixel_size_mm=p,
        shape=(H, W), coverage=float(reliable.mean()), height_above_mm=level.astype(np.float32),
        surface=surface, measurements=jm,
        meta={"seconds": seconds, "step_mm": step, "board_size_mm": list(board.size_mm),
              "board_outline_px": _outline_px(board, reg, (H, W), p),
              # the rig calibration the surface was corrected with (--calibration)
              "calibration": applied_calibration(surface.meta),
              # the field's share sharpest beyond each end of the sweep (not measured)
              "beyond_sweep": surface.meta.get("beyond_sweep")})
    log.info("inspected %d joints in %.2f s: %s", len(joints), seconds,
             ", ".join(f"{k} {v}" for k, v in result.counts().items() if v))
    return result


def _outline_px(board, reg: RegistrationResult, shape, p) -> list[list[float]]:
    from ._geometry import world_to_pixel

    poly = apply2d(reg.transform, board.outline_mm())
    return world_to_pixel(poly, shape=shape, pixel_size_mm=p).round(2).tolist()



def _board_plane(x, y, height, reliable, cfg: InspectConfig):
    """Board plane from the lowest reliable points, then from all points near it."""
    h = height[reliable]
    low = float(np.percentile(h, 2.0))
    cand = reliable & (height <= low + cfg.low_band_mm)
    plane = fit_board_plane(np.column_stack([x[cand], y[cand], height[cand]]),
                            distance_mm=cfg.plane_distance_mm, seed=cfg.seed)
    for _ in range(2):
        near = reliable & (np.abs(height - plane.z_mm(x, y)) <= cfg.low_band_mm / 2)
        if near.sum() < 50:
            break
        plane = fit_board_plane(np.column_stack([x[near], y[near], height[near]]),
                                distance_mm=cfg.plane_distance_mm, seed=cfg.seed)
    return plane
