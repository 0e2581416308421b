"""End to end: a focal stack (or a reconstruction) + a board file → reports.

:func:`inspect_stack` reconstructs the surface (:func:`smdinspect.sff.reconstruct`),
writes the reconstruction outputs (height map, confidence, all-in-focus image, cloud,
mesh), locates the board and judges every joint
(:func:`smdinspect.inspect.inspect_surface`), then writes ``report.json``,
``joints.csv``, ``junit.xml`` and ``report.html`` into ``out_dir``, each atomically,
and the board's IPC-CFX ``UnitsInspected`` message (``cfx_units_inspected.json``).
"""

from __future__ import annotations

import logging
import math
import os
import shutil
import tempfile
from pathlib import Path
from typing import Callable

import numpy as np

from ._json import read_json
from .errors import BoardNotLocatedError, InputError

__all__ = [
    "RECONSTRUCTION_FILES",
    "inspect_stack",
    "inspection_focus_config",
    "is_reconstruction",
    "load_reconstruction",
]

log = logging.getLogger(__name__)

#: Files that make a directory a reconstruction (as written by ``smdinspect reconstruct``).
RECONSTRUCTION_FILES = ("height_mm.tiff", "confidence.tiff", "summary.json")


def is_reconstruction(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a reconstruction output directory."""
    p = Path(path)
    return p.is_dir() and all((p / f).is_file() for f in RECONSTRUCTION_FILES)


def load_reconstruction(path: str | os.PathLike, *, pixel_size_mm: float | None = None):
    """Read a reconstruction directory back into a :class:`~smdinspect.sff.Surface`.

    ``reliable`` is ``confidence >= min_confidence`` of the settings in
    ``summary.json`` (0.5 when absent). ``sigma_mm.tiff`` is read when present, else the
    focus-curve widths are unknown (NaN) and so are the height uncertainties.
    """
    import tifffile

    from .sff import Surface
    from .stack import read_image

    root = Path(path)
    if not is_reconstruction(root):
        missing = [f for f in RECONSTRUCTION_FILES if not (root / f).is_file()]
        raise InputError(f"{root} is not a reconstruction directory (missing {', '.join(missing)})")
    summary = read_json(root / "summary.json")
    try:
        height = np.asarray(tifffile.imread(root / "height_mm.tiff"), np.float32)
        conf = np.asarray(tifffile.imread(root / "confidence.tiff"), np.float32)
    except (OSError, ValueError) as exc:
        raise InputError(f"{root}: cannot read the reconstruction: {exc}") from exc
    if height.shape != conf.shape or height.ndim != 2:
        raise InputError(f"{root}: height_mm.tiff {height.shape} and confidence.tiff "
                         f"{conf.shape} must be (H, W) of one shape")
    if not isinstance(summary, dict) or not isinstance(summary.get("config") or {}, dict):
        raise InputError(f"{root}: summary.json must hold the object smdinspect reconstruct "
                         f"writes (with a 'config' object); got {str(summary)[:40]}")
    min_conf = _summary_number(summary.get("config") or {}, "min_confidence", 0.5, root)
    sigma = np.full(height.shape, np.nan, np.float32)
    if (root / "sigma_mm.tiff").is_file():
        sigma = np.asarray(tifffile.imread(root / "sigma_mm.tiff"), np.float32)
    aif = read_image(root / "aif.png") if (root / "aif.png").is_file() else \
        np.zeros(height.shape, np.uint8)
    p = pixel_size_mm
    if p is None and summary.get("xy_units") != "px" and summary.get("pixel_size_mm") is not None:
        p = _summary_number(summary, "pixel_size_mm", 0.0, root)
    z_range = summary.get("z_range_mm") or [0.0, 0.0]
    if not isinstance(z_range, list) or len(z_range) != 2:
        raise InputError(f"{root}: summary.json z_range_mm must be [low, high]; got {z_range!r}")
    z0, z1 = (_summary_number({"z_range_mm": v}, "z_range_mm", 0.0, root) for v in z_range)
    step = _summary_number(summary, "step_mm", 0.0, root)
    n = int(round((z1 - z0) / step)) + 1 if step > 0 and z1 > z0 else 0
    z = z0 + step * np.arange(n) if 3 <= n <= 100_000 else np.array([z0, z1], float)
    reliable = (conf >= min_conf) & np.isfinite(height)
    return Surface(height_mm=height, confidence=conf, reliable=reliable,
                   f_peak=np.full(height.shape, np.nan, np.float32), sigma_mm=sigma,
                   reliability_db=np.full(height.shape, np.nan, np.float32), aif=aif,
                   pixel_size_mm=None if p is None else float(p), z_mm=z,
                   meta={"loaded_from": str(root), **summary})


def _summary_number(doc: dict, key: str, default: float, root: Path) -> float:
    value = doc.get(key)
    value = default if value is None else value
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
        raise InputError(f"{root}: summary.json {key} must be a number; got {value!r}")
    return float(value)


#: The inspection's focus window spans about this much of the board (mm): 5 px at the
#: 15-20 µm/px the defaults were set at, more pixels at a finer pixel size.
INSPECTION_WINDOW_MM = 0.07
#: ... and never fewer pixels than this.
INSPECTION_WINDOW_MIN_PX = 5


def inspection_window_px(pixel_size_mm: float | None) -> int:
    """The inspection's focus window side (odd, px) at ``pixel_size_mm``: the odd number
    nearest :data:`INSPECTION_WINDOW_MM` / pixel size, at least
    :data:`INSPECTION_WINDOW_MIN_PX` (5 px at 11.7 µm/px and coarser).

    A window of a fixed number of pixels shrinks on the board as the pixel size falls:
    at 7.5 µm/px a 5-px window spans 37 µm, too little texture for a clear focus peak,
    and most of every joint came out unreliable (demo board, seeds 3 and 7: 10 and 8 of
    18 joints; a 9-px window 3 and 3, as at 15 µm/px; at 10 µm/px 4 -> 3 with a 7-px
    window, and the insufficient joint found instead of unreliable).
    """
    if not pixel_size_mm or pixel_size_mm <= 0:
        return INSPECTION_WINDOW_MIN_PX
    side = 2 * int(math.floor(INSPECTION_WINDOW_MM / pixel_size_mm / 2)) + 1
    return max(INSPECTION_WINDOW_MIN_PX, side)


def stack_pixel_size(path) -> float | None:
    """The pixel size a stack folder's stack.json gives; None when it gives none or the
    folder is not a readable stack (the inspection then says what is wrong)."""
    from .stack import FocalStack

    try:
        return FocalStack.open(path).pixel_size_mm
    except InputError:
        return None


def inspection_focus_config(pixel_size_mm: float | None = None):
    """The focus settings inspection uses by default: a 5-pixel window (more at a pixel
    size finer than 11.7 µm: :func:`inspection_window_px`).

    Solder fillets are steep and narrow; the reconstruction default (9 px) spreads every
    body edge over the fillet next to it and smooths the fillet itself. On the synthetic
    boards (20 µm/px) a 5-px window halved the contaminated band and tracked the fillet
    profile within ~20 %, while edge pixels came out unreliable instead of wrong.
    No coarse focus level: its window (~24 px, 0.5 mm at 20 µm/px) is wider than a
    0402 fillet, so it would fill a fillet with the height of the body next to it. No
    support check: the top of a low fillet is a band of single reliable pixels that no
    window 5 px away repeats, and a joint is judged on a robust fit over its pad, not on
    single pixels. A 3-px own window (``own_window_px``): a fillet pixel whose 5-px window
    borrows the height of the termination or body edge next to it is unreliable instead
    of wrong (through shape from focus, tuning seeds 8-27: reliable pixels 0.3-0.5 of
    the way up good chip fillets off by > 0.1 mm, their 90th percentile 0.35 -> 0.06-0.10
    mm; recall 0.898 -> 0.910, right class 0.855 -> 0.867, false calls 3 -> 3, joints
    unreliable 23.7 -> 24.3 %). No gap-spanning depth-edge square (``edge_gap_check``): at
    the knee of a gull-wing lead it takes the top of the heel fillet too (the heel fit's
    spread over re-placed sweeps went from 5.0 to 6.7 µm,
    tests/inspect/test_max_height_repeatability).
    The operator's curve shape (``fit_power=None``), not one chosen per sweep: the choice
    varies with the placement and adds to the gauge's spread (demo board, 6 re-placed
    sweeps: %GR&R SOIC-8 / 0805 / 0603 4.6 / 5.1 / 7.7 % fixed, 5.5 / 5.9 / 8.2 % chosen).
    No noise pre-filter (``prefilter_px=0``): it widens the 5-px footprint that the
    fillet profiles and the gauge figures above were measured with. No precision cue
    (``precision_check``): a joint is a robust fit over its pad's pixels, and dropping
    the noisier fillet pixels left gull-wing heels without readings (demo-board GR&R,
    3 sweeps: SOIC-8 parts read 8 -> 6). No local plane over the heights
    (``plane_px``): a joint's fit already averages its pixels, and a 5-px plane on a
    5-px window widens the footprint the fillet profiles were measured with.
    """
    from .sff import FocusConfig

    return FocusConfig(window_px=inspection_window_px(pixel_size_mm), halo_ratio=8.0,
                       coarse_factor=0, support_steps=0,
                       own_window_px=3, edge_gap_check=False, fit_power=None, prefilter_px=0.0,
                       precision_check=False, plane_px=0)


def inspection_outputs() -> tuple[str, ...]:
    """Every file :func:`inspect_stack` may write into its output folder (the
    reconstruction's, the reports and the IPC-CFX message): what a later run may replace
    there (``_atomic.replace_dir``)."""
    from .inspect import REPORT_FILES
    from .inspect._cfx import CFX_FILE
    from .sff._export import RECONSTRUCTION_OUTPUTS

    return (*RECONSTRUCTION_OUTPUTS, *REPORT_FILES, CFX_FILE)


def inspect_stack(
    stack,
    board,
    out_dir: str | os.PathLike,
    *,
    focus_config=None,
    inspect_config=None,
    keep_unreliable: bool = False,
    cloud_filled: bool = False,
    progress: Callable[[int, int], None] | None = None,
    html: bool = True,
    source: str | None = None,
    calibration: str | os.PathLike | None = None,
):
    """Reconstruct, locate, measure, judge and report one board.

    Parameters
    ----------
    stack : FocalStack, Surface, or path
        A :class:`~smdinspect.stack.FocalStack`, a stack directory (``stack.json``), a
        reconstruction directory (see :func:`load_reconstruction`; then nothing is
        reconstructed) or an already reconstructed :class:`~smdinspect.sff.Surface`.
    board : Board or path
        The reference board or its file.
    out_dir : path
        Receives the reconstruction outputs (unless the input was one) and the reports.
    focus_config : FocusConfig, optional
        Default :func:`inspection_focus_config` (5-pixel focus window).
    inspect_config : InspectConfig, optional
    keep_unreliable : bool
        Keep unreliable points in the exported cloud and mesh.
    cloud_filled : bool
        ``cloud.ply`` also holds the dense surface's filled points, each flagged
        ``filled = 1`` (not with ``keep_unreliable``). The joints are judged on measured
        pixels only either way.
    progress : callable(done, total), optional
        Called once per frame while reconstructing.
    html : bool
        Write ``report.html`` too.
    source : str, optional
        What the measurement came from, for the reports (default: the stack's path).
    calibration : path, optional
        A rig calibration file (``smdinspect calibrate``): its focal-plane correction and
        z scale are applied to the surface before it is written and judged. Refused for
        a reconstruction that was corrected already.

    Returns
    -------
    InspectionResult
        ``result.exit_code`` is 0 when no joint is defective, 1 otherwise.

    Raises
    ------
    BoardNotLocatedError
        The board was not found (exit code 3); ``report.json`` with ``"status":
        "not_located"`` and the reason (and ``report.html`` showing why) is written first.
    InputError
        Bad stack, board file or settings.
    """
    from .calibrate import APPLIED_META_KEYS, applied_calibration, apply_calibration_file
    from .inspect import load_board
    from .inspect._cfx import write_units_inspected
    from .inspect._board import check_board_in_field
    from .inspect._inspect import inspect_surface
    from .inspect._report import write_not_located, write_reports
    from .sff import Surface, reconstruct
    from .sff._export import check_cloud_options
    from .stack import FocalStack

    check_cloud_options(keep_unreliable, cloud_filled)
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out} exists and is not a directory")
    if not hasattr(board, "components"):
        board = load_board(board)
    surface = None
    if isinstance(stack, Surface):
        surface = stack
        source = source or str(stack.meta.get("loaded_from", "<surface>"))
    elif isinstance(stack, FocalStack):
        source = source or (str(stack.root) if stack.root is not None else "<image list>")
    elif isinstance(stack, (str, os.PathLike)):
        source = source or str(stack)
        if is_reconstruction(stack):
            surface = load_reconstruction(stack)
        else:
            stack = FocalStack.open(stack)
    else:
        raise InputError(f"stack must be a FocalStack, a Surface or a path; got {type(stack).__name__}")
    if surface is not None and calibration is not None:
        done = applied_calibration(surface.meta)
        if done:
            raise InputError(f"{source} was already corrected by a calibration "
                             f"({', '.join(APPLIED_META_KEYS[k] for k in done)} in its "
                             "summary.json): inspect it without "
                             "--calibration")
    out.mkdir(parents=True, exist_ok=True)
    if surface is None:
        surface = reconstruct(stack, focus_config or inspection_focus_config(stack.pixel_size_mm),
                              progress=progress)
        surface = apply_calibration_file(surface, calibration)
        _write_reconstruction(surface, out, keep_unreliable, cloud_filled)
    else:
        surface = apply_calibration_file(surface, calibration)  # unchanged without one
    # The 3D view the reconstruction just rendered goes into report.html too.
    view3d = out / "view3d.png" if isinstance(stack, FocalStack) else None
    if surface.pixel_size_mm:
        # a board far larger than the field cannot be located, and registration would
        # allocate for its whole area (batch and Python callers reach this, not the CLI's check)
        check_board_in_field(board, surface.shape, surface.pixel_size_mm)
    log.info("locating board %r and measuring its %d joints", board.name, len(board.joints()))
    try:
        result = inspect_surface(surface, board, inspect_config)
    except BoardNotLocatedError as exc:
        write_not_located(out, board, getattr(exc, "registration", None), reason=str(exc),
                          source=source, shape=surface.shape, pixel_size_mm=surface.pixel_size_mm,
                          surface=surface, html_report=html, view3d_png=view3d)
        write_units_inspected(out)  # the IPC-CFX message, from the report.json just written
        raise
    write_reports(result, out, source=source, html_report=html, view3d_png=view3d)
    write_units_inspected(out)
    return result


def _write_reconstruction(surface, out: Path, keep_unreliable: bool,
                          cloud_filled: bool = False) -> None:
    """Write the reconstruction into a temporary sibling folder, then move it in."""
    from .sff import write_reconstruction

    with tempfile.TemporaryDirectory(dir=out, prefix=".partial-") as tmp:
        write_reconstruction(surface, tmp, keep_unreliable=keep_unreliable,
                             cloud_filled=cloud_filled)
        for f in Path(tmp).iterdir():
            shutil.move(str(f), out / f.name)
