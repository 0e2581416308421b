"""Offscreen 3D render of a height field: the ``view3d.png`` users open first.

The height map becomes a triangulated, lit, perspective mesh textured with the
all-in-focus colours, drawn with VTK into an offscreen OpenGL context (EGL through
Mesa's software rasteriser, so it needs no GPU and no display; OSMesa is the fallback).
VTK is imported inside :func:`render_height_field`; ``import smdinspect.sff`` stays light.
"""

from __future__ import annotations

import logging
import math
import os
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from .. import _atomic
from ..errors import InputError

__all__ = ["render_height_field"]

log = logging.getLogger(__name__)

VIEW_MAX_SIDE = 384  # the rendered mesh is at most this many vertices a side
TEXTURE_MAX_SIDE = 2048  # the colour texture is downsampled beyond this (the render is 1280 px wide)
GREY_RGB = (150, 150, 150)  # pixels without a valid height
BACKGROUND_TOP = (1.0, 1.0, 1.0)
BACKGROUND_BOTTOM = (0.86, 0.88, 0.91)
FADE_FILLED = 0.35  # filled (not measured) pixels: this much of their colour turns grey
MIN_VALID_OF_BLOCK = 0.25  # a decimated vertex needs this fraction of its block valid
RELIEF_OF_FIELD = 0.22  # auto exaggeration aims at relief ≈ this fraction of the field


def render_height_field(
    height_mm: np.ndarray,
    rgb: np.ndarray,
    valid: np.ndarray | None,
    *,
    pixel_size_mm: float | None,
    out_path: str | os.PathLike | None = None,
    size_px: tuple[int, int] = (1280, 960),
    z_exaggeration: float | None = None,
    filled: np.ndarray | None = None,
    max_side: int = VIEW_MAX_SIDE,
    elevation_deg: float = 55.0,
    azimuth_deg: float = -20.0,
    title: str = "3D view",
) -> np.ndarray:
    """Render a height field as a textured, lit, perspective 3D view.

    The surface is seen from the front (the image's bottom edge) and slightly to the
    left, ``elevation_deg`` above the board, with a headlight and a key light from the
    upper left; the board stands on a grey plinth against a light background. Axes give
    x, y and z in mm (x, y in pixels when ``pixel_size_mm`` is None); the vertical
    exaggeration is written on the picture. Heights are clipped to the 0.1–99.9
    percentile range of the measured ones (the filled ones when fewer than
    :data:`MIN_MEASURED_FOR_RANGE` are measured), plus a 5 % margin, for the picture
    only, so one spike or a filled guess cannot flatten the rest. The render is
    deterministic: the same input gives the same image.

    Parameters
    ----------
    height_mm : (H, W) float
        Height of every pixel above the board, in mm. Pixels whose height is not
        finite are treated as not valid.
    rgb : (H, W, 3) or (H, W) uint8, uint16 or float in [0, 1]
        Colour of every pixel (the all-in-focus image), RGB order.
    valid : (H, W) bool or None
        Pixels with a usable height; the others are drawn neutral grey at a height
        taken from their valid neighbours. None means every finite pixel.
    pixel_size_mm : float or None
        Object-side pixel size in mm; None when unknown (x, y are then in pixels and
        the heights are scaled to them for display, as the picture says).
    out_path : path, optional
        Also write the image there as a PNG (atomically).
    size_px : (width, height)
        Size of the image in pixels.
    z_exaggeration : float, optional
        Vertical exaggeration (with ``pixel_size_mm`` None: drawn pixels per mm of
        height). None picks a round factor that makes the relief about a fifth of the
        field (never below 1 when the pixel size is known).
    filled : (H, W) bool, optional
        Pixels whose height was filled in rather than measured: drawn with their colour
        faded towards grey.
    max_side : int
        The mesh is decimated (block means of the valid heights, then a 3 x 3 median
        against lone spikes; display only) to at most this many vertices a side; the
        colours keep their full resolution as a texture (up to 4096 px a side).
    elevation_deg, azimuth_deg : float
        Camera direction: degrees above the board plane, and degrees around the
        vertical from straight in front (negative: from the left).
    title : str
        First line of the caption.

    Returns
    -------
    (size_px[1], size_px[0], 3) uint8
        The rendered image, RGB.

    Raises
    ------
    InputError
        An argument has the wrong shape, type or value.
    ImportError
        VTK is not installed, or no offscreen OpenGL context can be made.
    """
    height, colours, ok, fade = _check_inputs(height_mm, rgb, valid, filled)
    pixel_size_mm = _check_pixel_size(pixel_size_mm)
    width_px, height_px = _check_size(size_px)
    if z_exaggeration is not None:
        z_exaggeration = _positive(z_exaggeration, "z_exaggeration")
    if isinstance(max_side, bool) or not isinstance(max_side, (int, np.integer)) or max_side < 2:
        raise InputError(f"max_side must be an integer >= 2; got {max_side!r}")
    elevation_deg = float(elevation_deg)
    if not 5.0 <= elevation_deg <= 90.0:
        raise InputError(f"elevation_deg must be in [5, 90]; got {elevation_deg}")
    azimuth_deg = float(azimuth_deg)
    if not -90.0 <= azimuth_deg <= 90.0:
        raise InputError(f"azimuth_deg must be in [-90, 90]; got {azimuth_deg}")

    scene = _build_scene(height, colours, ok, fade, pixel_size_mm=pixel_size_mm,
                         z_exaggeration=z_exaggeration, max_side=int(max_side))
    image = _render(scene, width_px=width_px, height_px=height_px,
                    elevation_deg=elevation_deg, azimuth_deg=azimuth_deg, title=str(title))
    if out_path is not None:
        _write_png(out_path, image)
    return image


def _write_png(path, image: np.ndarray) -> Path:
    import cv2

    ok, buf = cv2.imencode(".png", np.ascontiguousarray(image[:, :, ::-1]))
    if not ok:  # pragma: no cover
        raise OSError(f"could not encode the 3D view for {path}")
    return _atomic.write_bytes(path, buf.tobytes())


# --------------------------------------------------------------------------- checks


def _check_inputs(height_mm, rgb, valid, filled):
    if not isinstance(height_mm, np.ndarray):
        height_mm = np.asarray(height_mm)
    if height_mm.ndim != 2 or min(height_mm.shape) < 2:
        raise InputError(f"height_mm must be a (H, W) array with H, W >= 2; got shape "
                         f"{height_mm.shape}")
    if height_mm.dtype == bool or not np.issubdtype(height_mm.dtype, np.number) \
            or np.issubdtype(height_mm.dtype, np.complexfloating):
        raise InputError(f"height_mm must be a real number array; got dtype {height_mm.dtype}")
    shape = height_mm.shape
    height = height_mm.astype(np.float32, copy=False)

    rgb = np.asarray(rgb)
    if rgb.ndim == 2:
        rgb = np.repeat(rgb[:, :, None], 3, axis=2)
    if rgb.ndim != 3 or rgb.shape[:2] != shape or rgb.shape[2] != 3:
        raise InputError(f"rgb must be a {shape + (3,)} colour image matching height_mm; got "
                         f"shape {rgb.shape}")
    if rgb.dtype == np.uint8:
        colours = rgb
    elif rgb.dtype == np.uint16:
        colours = (rgb.astype(np.float32) / 257.0 + 0.5).astype(np.uint8)
    elif np.issubdtype(rgb.dtype, np.floating):
        colours = (np.clip(np.nan_to_num(rgb.astype(np.float32)), 0.0, 1.0) * 255.0
                   + 0.5).astype(np.uint8)
    else:
        raise InputError(f"rgb must be uint8, uint16 or float in [0, 1]; got dtype {rgb.dtype}")

    ok = np.isfinite(height)
    if valid is not None:
        ok &= _mask(valid, "valid", shape)
    fade = None if filled is None else _mask(filled, "filled", shape)
    return height, np.ascontiguousarray(colours), ok, fade


def _mask(mask, name: str, shape) -> np.ndarray:
    mask = np.asarray(mask)
    if mask.shape != shape:
        raise InputError(f"{name} must be a {shape} mask matching height_mm; got shape {mask.shape}")
    if mask.dtype != bool and not np.issubdtype(mask.dtype, np.integer):
        raise InputError(f"{name} must be a bool mask; got dtype {mask.dtype}")
    return mask.astype(bool, copy=False)


def _check_pixel_size(pixel_size_mm):
    if pixel_size_mm is None:
        return None
    return _positive(pixel_size_mm, "pixel_size_mm")


def _positive(value, name: str) -> float:
    try:
        if isinstance(value, bool):
            raise TypeError
        v = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a number > 0; got {value!r}") from None
    if not math.isfinite(v) or v <= 0:
        raise InputError(f"{name} must be a finite number > 0; got {value!r}")
    return v


def _check_size(size_px) -> tuple[int, int]:
    try:
        w, h = size_px
        if any(isinstance(v, bool) or int(v) != v for v in (w, h)):
            raise ValueError
        w, h = int(w), int(h)
    except (TypeError, ValueError):
        raise InputError(f"size_px must be (width, height) in whole pixels; got {size_px!r}") from None
    if not (64 <= w <= 8192 and 64 <= h <= 8192):
        raise InputError(f"size_px must be between 64 and 8192 pixels a side; got {size_px!r}")
    return w, h


# --------------------------------------------------------------------------- geometry


def _nice(x: float) -> float:
    """The largest of 1, 1.5, 2, 3, 5, 7.5 × 10^k not above ``x``."""
    if x <= 0:
        return 1.0
    e = 10.0 ** math.floor(math.log10(x))
    best = e
    for m in (1.0, 1.5, 2.0, 3.0, 5.0, 7.5):
        if m * e <= x * (1 + 1e-9):
            best = m * e
    return best


#: Measured (not filled) valid pixels needed for them alone to set the height range.
MIN_MEASURED_FOR_RANGE = 100


def _build_scene(height, colours, ok, fade, *, pixel_size_mm, z_exaggeration, max_side):
    import cv2

    h, w = height.shape
    step = max(1, int(math.ceil(max(h, w) / max_side)))
    rows = np.unique(np.r_[np.arange(0, h, step), h - 1])
    cols = np.unique(np.r_[np.arange(0, w, step), w - 1])

    # block means of the valid heights around every vertex, weighted by how many are valid
    hs, ns, area = _block_sums(height, ok, rows, cols, step)
    weight = ns / area
    weight[weight < MIN_VALID_OF_BLOCK] = 0.0  # a few stray valid pixels are no height
    z = np.divide(hs, ns, out=np.zeros_like(hs), where=ns > 0)

    n_valid = int(ok.sum())
    if n_valid:
        # the range from the measured heights when there are enough: filled ones are
        # guesses (a few filled from a sweep's far end flattened a real flat target)
        measured = ok & ~fade if fade is not None else ok
        ranged = height[measured] if measured.sum() >= MIN_MEASURED_FOR_RANGE else height[ok]
        lo, hi = np.percentile(ranged, [0.1, 99.9])
        margin = 0.05 * (hi - lo)
        z = _fill_invalid(np.clip(z, lo - margin, hi + margin), weight)
        z = cv2.medianBlur(z.astype(np.float32), 3).astype(np.float64)  # tame lone spikes
        zlo, zhi = float(z.min()), float(z.max())
    else:
        z = np.zeros(z.shape, np.float64)
        zlo = zhi = 0.0
    zspan = zhi - zlo

    p = 1.0 if pixel_size_mm is None else pixel_size_mm
    xs = cols.astype(np.float64) * p
    ys = (h - 1 - rows.astype(np.float64)) * p
    field = max(xs[-1] - xs[0], ys[0] - ys[-1])
    if z_exaggeration is None:
        if zspan > 1e-9:
            ex = _nice(RELIEF_OF_FIELD * field / zspan)
            if pixel_size_mm is not None:
                ex = max(1.0, ex)
        else:
            ex = 1.0
    else:
        ex = z_exaggeration
    thickness = max(0.04 * field, 0.25 * zspan * ex)
    base = zlo * ex - thickness  # drawn z of the plinth's bottom

    # the texture: full-resolution colours, invalid grey, filled faded
    tex = colours
    if fade is not None and fade.any():
        # per-channel look-up tables (the fade only depends on the value): the same
        # numbers as blending the faded pixels one by one, 20x faster on 3 Mpixel
        v = np.arange(256, dtype=np.float64)
        lut = np.stack([(v * (1 - FADE_FILLED) + g * FADE_FILLED + 0.5).astype(np.uint8)
                        for g in np.asarray(GREY_RGB, np.float32)], axis=1)
        tex = cv2.LUT(colours, lut[None])  # colours: (H, W, 3) uint8
        np.copyto(tex, colours, where=~fade[:, :, None])
    if not ok.all():
        tex = tex.copy() if tex is colours else tex
        np.copyto(tex, np.asarray(GREY_RGB, np.uint8), where=~ok[:, :, None])
    tscale = min(1.0, TEXTURE_MAX_SIDE / max(h, w))
    if tscale < 1.0:
        tex = cv2.resize(tex, (max(2, round(w * tscale)), max(2, round(h * tscale))),
                         interpolation=cv2.INTER_AREA)

    units = "mm" if pixel_size_mm is not None else "px"
    return SimpleNamespace(xs=xs, ys=ys, z_mm=z, ex=ex, base=base, texture=np.ascontiguousarray(tex),
                  rows=rows, cols=cols, shape=(h, w), units=units, zlo=zlo, zhi=zhi,
                  pixel_size_mm=pixel_size_mm, n_valid=n_valid, coverage=n_valid / ok.size,
                  filled_share=0.0 if fade is None else float((fade & ok).mean()), step=step)


def _block_sums(height, ok, rows, cols, step: int):
    """Sums over the ``step`` x ``step`` box around each grid vertex (``rows`` x
    ``cols``; the box of ``cv2.boxFilter(normalize=False)``, zero outside the image): of
    the valid heights, of the valid pixels, and of the pixels inside the image.

    Only the boxes' rows and columns are visited (no full-resolution temporaries).

    Returns
    -------
    hs, ns, area : (len(rows), len(cols)) float32
    """
    h, w = height.shape
    offsets = np.arange(step) - step // 2
    rr, cc = rows[:, None] + offsets, cols[:, None] + offsets
    r_in, c_in = (rr >= 0) & (rr < h), (cc >= 0) & (cc < w)
    rr, cc = np.clip(rr, 0, h - 1), np.clip(cc, 0, w - 1)
    hs_rows = np.zeros((len(rows), w), np.float64)
    ns_rows = np.zeros((len(rows), w), np.float64)
    for k in range(step):  # sums down the boxes' rows, at every column
        valid = ok[rr[:, k]] & r_in[:, k, None]
        hs_rows += np.where(valid, height[rr[:, k]], 0.0)
        ns_rows += valid
    hs = np.zeros((len(rows), len(cols)), np.float64)
    ns = np.zeros_like(hs)
    for k in range(step):  # then across the boxes' columns
        hs += hs_rows[:, cc[:, k]] * c_in[None, :, k]
        ns += ns_rows[:, cc[:, k]] * c_in[None, :, k]
    area = r_in.sum(axis=1)[:, None] * c_in.sum(axis=1)[None, :]
    return hs.astype(np.float32), ns.astype(np.float32), area.astype(np.float32)


def _fill_invalid(height: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Heights where ``weight`` (0..1, 0: no valid height) is low, from the neighbours.

    Push-pull interpolation (a Gaussian pyramid of weighted sums, then blended back up),
    for the picture only: smooth, fast, and the valid heights keep their values.

    Parameters
    ----------
    height : (H, W) float
    weight : (H, W) float or bool
        1 where the height is fully valid, 0 where it is missing.

    Returns
    -------
    (H, W) float32
    """
    import cv2

    w = np.clip(np.asarray(weight, np.float32), 0.0, 1.0)
    z = np.where(w > 0, np.asarray(height, np.float32), 0.0).astype(np.float32)
    if w.min() >= 1.0:
        return z
    if w.max() <= 0.0:
        return np.zeros_like(z)
    nums, dens = [z * w], [w]
    while min(nums[-1].shape) > 2:
        nums.append(cv2.pyrDown(nums[-1]))
        dens.append(cv2.pyrDown(dens[-1]))
    num, den = nums[-1], dens[-1]
    total = float(den.sum())
    est = np.where(den > 1e-6, num / np.maximum(den, 1e-6),
                   float(num.sum()) / total if total > 0 else 0.0).astype(np.float32)
    for num, den in zip(nums[-2::-1], dens[-2::-1]):
        up = cv2.pyrUp(est, dstsize=(num.shape[1], num.shape[0]))
        a = np.clip(den, 0.0, 1.0)
        est = (a * np.divide(num, den, out=up.copy(), where=den > 1e-6) + (1 - a) * up)
        est = est.astype(np.float32)
    return np.where(w >= 1.0, z, est).astype(np.float32)


def _surface_polydata(scene):
    """The textured surface as vtkPolyData (points, triangles, normals, texture coords)."""
    from vtkmodules.util.numpy_support import numpy_to_vtk, numpy_to_vtkIdTypeArray
    from vtkmodules.vtkCommonCore import vtkPoints
    from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkPolyData

    xs, ys = scene.xs, scene.ys
    zd = scene.z_mm * scene.ex
    gh, gw = zd.shape
    xg, yg = np.meshgrid(xs, ys)
    pts = np.column_stack([xg.ravel(), yg.ravel(), zd.ravel()])

    # vertex normals from the drawn (exaggerated) grid
    dz_drow, dz_dcol = np.gradient(zd, ys, xs)  # ys: world y of each row
    n = np.dstack([-dz_dcol, -dz_drow, np.ones_like(zd)]).reshape(-1, 3)
    n /= np.linalg.norm(n, axis=1, keepdims=True)

    h, w = scene.shape
    u = (scene.cols + 0.5) / w
    v = (scene.rows + 0.5) / h  # the texture is handed over top row first (see _render)
    ug, vg = np.meshgrid(u, v)
    tc = np.column_stack([ug.ravel(), vg.ravel()])

    idx = np.arange(gh * gw).reshape(gh, gw)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    # rows go down the image (y decreases), so (a, c, b) is counter-clockwise from +z
    tri = np.concatenate([np.column_stack([a, c, b]), np.column_stack([b, c, d])])

    poly = vtkPolyData()
    points = vtkPoints()
    points.SetData(numpy_to_vtk(np.ascontiguousarray(pts, np.float32), deep=True))
    poly.SetPoints(points)
    cells = vtkCellArray()
    offsets = np.arange(0, 3 * len(tri) + 1, 3, dtype=np.int64)
    cells.SetData(numpy_to_vtkIdTypeArray(offsets, deep=True),
                  numpy_to_vtkIdTypeArray(tri.astype(np.int64).ravel(), deep=True))
    poly.SetPolys(cells)
    normals = numpy_to_vtk(np.ascontiguousarray(n, np.float32), deep=True)
    normals.SetName("Normals")
    poly.GetPointData().SetNormals(normals)
    tcoords = numpy_to_vtk(np.ascontiguousarray(tc, np.float32), deep=True)
    tcoords.SetName("TCoords")
    poly.GetPointData().SetTCoords(tcoords)
    return poly


def _plinth_polydata(scene):
    """Side walls from the surface's edge down to a flat bottom, so it reads as a solid."""
    from vtkmodules.util.numpy_support import numpy_to_vtk, numpy_to_vtkIdTypeArray
    from vtkmodules.vtkCommonCore import vtkPoints
    from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkPolyData

    zd = scene.z_mm * scene.ex
    gh, gw = zd.shape
    xs, ys = scene.xs, scene.ys
    # the border, walked once around: top row, right column, bottom row, left column
    r = np.r_[np.zeros(gw - 1, int), np.arange(gh - 1), np.full(gw - 1, gh - 1),
              np.arange(gh - 1, 0, -1)]
    c = np.r_[np.arange(gw - 1), np.full(gh - 1, gw - 1), np.arange(gw - 1, 0, -1),
              np.zeros(gh - 1, int)]
    m = len(r)
    top = np.column_stack([xs[c], ys[r], zd[r, c]])
    bottom = np.column_stack([xs[c], ys[r], np.full(m, scene.base)])
    pts = np.vstack([top, bottom])
    i = np.arange(m)
    j = (i + 1) % m
    quads = np.column_stack([i, j, j + m, i + m])
    floor = np.arange(2 * m - 1, m - 1, -1)  # the bottom, facing down
    conn = np.r_[quads.ravel(), floor]
    offsets = np.r_[np.arange(0, 4 * m + 1, 4), 4 * m + m].astype(np.int64)

    poly = vtkPolyData()
    points = vtkPoints()
    points.SetData(numpy_to_vtk(np.ascontiguousarray(pts, np.float32), deep=True))
    poly.SetPoints(points)
    cells = vtkCellArray()
    cells.SetData(numpy_to_vtkIdTypeArray(offsets, deep=True),
                  numpy_to_vtkIdTypeArray(conn.astype(np.int64), deep=True))
    poly.SetPolys(cells)
    return poly


# --------------------------------------------------------------------------- rendering


def _vtk():
    try:
        import vtkmodules.vtkRenderingOpenGL2  # noqa: F401  (OpenGL back end)
        import vtkmodules.vtkRenderingFreeType  # noqa: F401  (text)
        from vtkmodules import vtkRenderingCore, vtkRenderingAnnotation
    except ImportError as exc:  # pragma: no cover - depends on the machine
        raise ImportError(
            f"the 3D view needs VTK >= 9.4 ({exc}); install it with "
            "'.venv/bin/python -m pip install vtk' or run scripts/setup.sh"
        ) from None
    return vtkRenderingCore, vtkRenderingAnnotation


def _offscreen_window(width_px: int, height_px: int):
    """An offscreen render window: EGL (Mesa llvmpipe on a CPU-only machine), else OSMesa."""
    import ctypes.util

    from vtkmodules.vtkRenderingOpenGL2 import vtkEGLRenderWindow, vtkOSOpenGLRenderWindow

    tried = []
    candidates = [("EGL", vtkEGLRenderWindow)]
    if ctypes.util.find_library("OSMesa"):  # vtkOSOpenGLRenderWindow crashes without it
        candidates.append(("OSMesa", vtkOSOpenGLRenderWindow))
    for name, cls in candidates:
        win = cls()
        win.SetOffScreenRendering(1)
        win.SetSize(width_px, height_px)
        win.SetMultiSamples(0)
        win.Initialize()
        if win.GetGenericContext() is not None:  # IsCurrent() is True even on failure
            log.debug("3D view: offscreen OpenGL through %s", name)
            return win
        tried.append(name)
    raise ImportError(
        f"the 3D view needs an offscreen OpenGL context and none could be made (tried "
        f"{', '.join(tried)}); on Debian install libegl1, libegl-mesa0 and libgl1-mesa-dri "
        "(scripts/setup.sh does), or libosmesa6"
    )


def _format_mm(v: float) -> str:
    return f"{v:.3g}"


def _render(scene, *, width_px, height_px, elevation_deg, azimuth_deg, title) -> np.ndarray:
    core, annotation = _vtk()
    from vtkmodules.util.numpy_support import numpy_to_vtk, vtk_to_numpy
    from vtkmodules.vtkCommonDataModel import vtkImageData

    win = _offscreen_window(width_px, height_px)
    try:
        ren = core.vtkRenderer()
        win.AddRenderer(ren)
        ren.SetBackground(*BACKGROUND_BOTTOM)
        ren.SetBackground2(*BACKGROUND_TOP)
        ren.GradientBackgroundOn()

        # surface, textured with the colours
        th, tw = scene.texture.shape[:2]
        img = vtkImageData()
        img.SetDimensions(tw, th, 1)
        # VTK images start at the bottom row; the texture goes in as it is (no copy:
        # ``texels`` stays referenced until the render is read back) and the surface's
        # texture coordinates count rows from the top instead
        texels = np.ascontiguousarray(scene.texture).reshape(-1, 3)
        arr = numpy_to_vtk(texels, deep=False)
        arr.SetName("rgb")
        img.GetPointData().SetScalars(arr)
        texture = core.vtkTexture()
        texture.SetInputData(img)
        texture.InterpolateOn()
        texture.MipmapOn()
        texture.SetColorModeToDirectScalars()
        mapper = core.vtkPolyDataMapper()
        mapper.SetInputData(_surface_polydata(scene))
        mapper.ScalarVisibilityOff()
        surf = core.vtkActor()
        surf.SetMapper(mapper)
        surf.SetTexture(texture)
        prop = surf.GetProperty()
        prop.SetInterpolationToGouraud()
        prop.SetAmbient(0.32)
        prop.SetDiffuse(0.90)
        prop.SetSpecular(0.08)
        prop.SetSpecularPower(20)
        ren.AddActor(surf)

        plinth_mapper = core.vtkPolyDataMapper()
        plinth_mapper.SetInputData(_plinth_polydata(scene))
        plinth = core.vtkActor()
        plinth.SetMapper(plinth_mapper)
        pp = plinth.GetProperty()
        pp.SetColor(0.80, 0.81, 0.83)
        pp.SetInterpolationToFlat()
        pp.SetAmbient(0.35)
        pp.SetDiffuse(0.65)
        ren.AddActor(plinth)

        # lights: a headlight and a key light from the upper left of the camera
        ren.RemoveAllLights()
        ren.AutomaticLightCreationOff()
        head = core.vtkLight()
        head.SetLightTypeToHeadlight()
        head.SetIntensity(0.60)
        ren.AddLight(head)
        key = core.vtkLight()
        key.SetLightTypeToCameraLight()
        key.SetPosition(-1.0, 1.0, 0.6)
        key.SetFocalPoint(0.0, 0.0, 0.0)
        key.SetIntensity(0.55)
        ren.AddLight(key)

        x0, x1, y0, y1 = scene.xs[0], scene.xs[-1], scene.ys[-1], scene.ys[0]
        z0, z1 = scene.zlo * scene.ex, max(scene.zhi * scene.ex, scene.zlo * scene.ex + 1e-9)
        # frame what is drawn: the surface, the plinth's bottom, the z axis (front corner)
        zd = scene.z_mm * scene.ex
        sub = max(1, max(zd.shape) // 96)
        xg, yg = np.meshgrid(scene.xs[::sub], scene.ys[::sub])
        bar = _z_bar(core, scene, height_px)
        fit = np.vstack([
            np.column_stack([xg.ravel(), yg.ravel(), zd[::sub, ::sub].ravel()]),
            [[x, y, scene.base] for x in (x0, x1) for y in (y0, y1)],
            bar.fit_points,
        ])
        cam = ren.GetActiveCamera()
        _place_camera(cam, fit, aspect=width_px / height_px, elevation_deg=elevation_deg,
                      azimuth_deg=azimuth_deg)
        ren.AddActor(_axes(annotation, scene, (x0, x1, y0, y1, z0, z1), cam))
        for prop in bar.props:
            ren.AddViewProp(prop)
        ren.ResetCameraClippingRange()
        for text, corner, size in _captions(scene, title):
            ren.AddViewProp(_text(core, text, corner, size, height_px))

        win.Render()
        buf = vtk_to_numpy(_read_pixels(win))
        image = buf.reshape(height_px, width_px, -1)[::-1, :, :3].copy()
    finally:
        win.Finalize()
    return image


def _read_pixels(win):
    from vtkmodules.vtkCommonCore import vtkUnsignedCharArray

    w, h = win.GetSize()
    data = vtkUnsignedCharArray()
    win.GetPixelData(0, 0, w - 1, h - 1, 0, data, 0)  # back buffer, RGB
    return data


def _place_camera(cam, corners, *, aspect, elevation_deg, azimuth_deg, view_angle_deg=28.0,
                  window=(-0.86, 0.86, -0.76, 0.80)):
    """Aim a perspective camera so the points ``corners`` (n, 3) just fill ``window``.

    ``window`` is (left, right, bottom, top) in normalised screen coordinates (-1..1);
    what is outside it is left for the axes' labels and the captions.
    """
    el, az = math.radians(elevation_deg), math.radians(azimuth_deg)
    back = np.array([math.sin(az) * math.cos(el), -math.cos(az) * math.cos(el), math.sin(el)])
    right = np.cross(-back, [0.0, 0.0, 1.0])
    if np.linalg.norm(right) < 1e-9:  # looking straight down
        right = np.array([math.cos(az), math.sin(az), 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, -back)
    ty = math.tan(math.radians(view_angle_deg) / 2)
    tx = ty * aspect
    left, rightmost, bottom, top = window
    focal = corners.mean(axis=0)
    size = float(np.ptp(corners, axis=0).max()) or 1.0
    dist = 2.0 * size / ty
    for _ in range(12):  # scale and shift until the projected box fits the window
        rel = corners - focal
        depth = dist - rel @ back
        px = (rel @ right) / depth / tx
        py = (rel @ up) / depth / ty
        scale = max((px.max() - px.min()) / (rightmost - left),
                    (py.max() - py.min()) / (top - bottom))
        focal = focal + (right * ((px.max() + px.min()) / 2 - (left + rightmost) / 2) * tx
                         + up * ((py.max() + py.min()) / 2 - (bottom + top) / 2) * ty) * dist
        dist = max(dist * scale, 0.5 * size)
    cam.SetFocalPoint(*focal)
    cam.SetPosition(*(focal + back * dist))
    cam.SetViewUp(*up)
    cam.SetViewAngle(view_angle_deg)
    cam.SetClippingRange(max(dist - 2 * size, 1e-3 * dist), dist + 2 * size)


def _axes(annotation, scene, bounds, cam):
    axes = annotation.vtkCubeAxesActor()
    axes.SetBounds(*bounds)
    axes.SetCamera(cam)
    u = scene.units
    axes.SetXTitle(f"x ({u})")
    axes.SetYTitle(f"y ({u})")
    axes.ZAxisVisibilityOff()  # heights get their own scale bar (_z_bar)
    axes.ZAxisLabelVisibilityOff()
    axes.ZAxisTickVisibilityOff()
    axes.SetZTitle(" ")
    axes.SetXAxisRange(bounds[0], bounds[1])
    axes.SetYAxisRange(bounds[2], bounds[3])
    axes.SetFlyModeToOuterEdges()
    axes.SetGridLineLocation(axes.VTK_GRID_LINES_FURTHEST)
    axes.XAxisMinorTickVisibilityOff()
    axes.YAxisMinorTickVisibilityOff()
    axes.ZAxisMinorTickVisibilityOff()
    axes.SetLabelScaling(False, 0, 0, 0)
    axes.SetScreenSize(9.0)
    dark = (0.15, 0.15, 0.18)
    for i in range(3):
        axes.GetTitleTextProperty(i).SetColor(*dark)
        axes.GetLabelTextProperty(i).SetColor(*dark)
    for prop in (axes.GetXAxesLinesProperty(), axes.GetYAxesLinesProperty(),
                 axes.GetZAxesLinesProperty()):
        prop.SetColor(*dark)
    return axes


def _z_bar(core, scene, height_px):
    """A vertical scale bar of a round height in mm at the front right corner.

    Drawn exaggerated like the surface, labelled in true mm. Returns the props and the
    points the camera must keep in view.
    """
    from vtkmodules.util.numpy_support import numpy_to_vtk, numpy_to_vtkIdTypeArray
    from vtkmodules.vtkCommonCore import vtkPoints
    from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkPolyData

    x1, y0 = scene.xs[-1], scene.ys[-1]
    field = max(scene.xs[-1] - scene.xs[0], scene.ys[0] - scene.ys[-1])
    zspan = scene.zhi - scene.zlo
    out = SimpleNamespace(props=[], fit_points=np.empty((0, 3)))
    if zspan <= 1e-9:
        return out
    bar_mm = _nice(zspan)
    gap, cap = 0.03 * field, 0.012 * field
    xb, z0 = x1 + gap, scene.zlo * scene.ex
    z1 = z0 + bar_mm * scene.ex
    pts = np.array([[xb, y0, z0], [xb, y0, z1], [xb - cap, y0, z0], [xb + cap, y0, z0],
                    [xb - cap, y0, z1], [xb + cap, y0, z1]], np.float32)
    poly = vtkPolyData()
    points = vtkPoints()
    points.SetData(numpy_to_vtk(pts, deep=True))
    poly.SetPoints(points)
    lines = vtkCellArray()
    lines.SetData(numpy_to_vtkIdTypeArray(np.array([0, 2, 4, 6], np.int64), deep=True),
                  numpy_to_vtkIdTypeArray(np.arange(6, dtype=np.int64), deep=True))
    poly.SetLines(lines)
    mapper = core.vtkPolyDataMapper()
    mapper.SetInputData(poly)
    actor = core.vtkActor()
    actor.SetMapper(mapper)
    actor.GetProperty().SetColor(0.15, 0.15, 0.18)
    actor.GetProperty().SetLineWidth(2.0)
    actor.GetProperty().LightingOff()
    label = core.vtkBillboardTextActor3D()
    label.SetInput(f"z: {bar_mm:g} mm")
    label.SetPosition(xb + 1.5 * cap, y0, (z0 + z1) / 2)
    tp = label.GetTextProperty()
    tp.SetFontFamilyToArial()
    tp.SetFontSize(max(10, int(round(height_px / 56))))
    tp.SetColor(0.12, 0.12, 0.15)
    tp.SetJustificationToLeft()
    tp.SetVerticalJustificationToCentered()
    out.props = [actor, label]
    out.fit_points = np.vstack([pts, [[xb + 0.11 * field, y0, (z0 + z1) / 2]]])
    return out


def _captions(scene, title):
    if scene.pixel_size_mm is not None:
        scale = (f"x, y, z in mm; heights exaggerated ×{scene.ex:g}" if scene.ex != 1
                 else "x, y, z in mm; true proportions")
    else:
        scale = (f"pixel size unknown: x, y in pixels, z in mm drawn at {scene.ex:g} px per mm "
                 "(proportions not true)")
    lines = [(f"{title}  ·  {scale}", "top", 1.0)]
    notes = [f"heights {_format_mm(scene.zlo)} … {_format_mm(scene.zhi)} mm"]
    if scene.filled_share > 0:
        notes.append(f"faded: height filled in, not measured ({100 * scene.filled_share:.1f}%)")
    if scene.coverage < 1.0:
        notes.append(f"grey: no valid height ({100 * (1 - scene.coverage):.1f}%)")
    lines.append(("   ".join(notes), "bottom", 0.85))
    return lines


def _text(core, text, where, rel_size, height_px):
    actor = core.vtkTextActor()
    actor.SetInput(text)
    tp = actor.GetTextProperty()
    tp.SetFontFamilyToArial()
    tp.SetFontSize(max(10, int(round(height_px / 48 * rel_size))))
    tp.SetColor(0.12, 0.12, 0.15)
    tp.SetJustificationToCentered()
    coord = actor.GetPositionCoordinate()
    coord.SetCoordinateSystemToNormalizedViewport()
    if where == "top":
        tp.SetVerticalJustificationToTop()
        coord.SetValue(0.5, 0.975)
    else:
        tp.SetVerticalJustificationToBottom()
        coord.SetValue(0.5, 0.02)
    return actor
