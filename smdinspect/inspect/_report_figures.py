"""Pictures of ``report.html``: inline SVG over embedded PNGs.

Every picture is a small SVG drawn here by hand: the raster (all-in-focus image, height
map, crop) is a base64 PNG ``<image>``; outlines, labels, colour bars, scale bars and
the height profiles are vectors, so their text stays sharp at any zoom, is part of the
page's DOM (searchable, testable) and is HTML-escaped like every other text.

Coordinates: image pixels are (col, row) with the pixel centre at integer values (the
convention of ``JointResult.polygon_px``); a picture shows pixel ``i`` over
``[i - 0.5, i + 0.5]`` scaled by the picture's scale, so a point ``c`` is drawn at
``(c - c0 + 0.5) * scale`` for a picture starting at pixel ``c0``.
"""

from __future__ import annotations

import base64
import html
import math
from dataclasses import dataclass

import numpy as np

__all__ = [
    "PadMark",
    "colour_bar_svg",
    "colourise",
    "crop_svg",
    "esc",
    "height_range",
    "joint_profile",
    "jpeg_data_uri",
    "nice_length",
    "nice_ticks",
    "overview_svg",
    "place_labels",
    "png_data_uri",
    "profile_svg",
    "resize",
    "rgb_css",
]

#: Colour map of every height picture (and its colour bar).
CMAP = "viridis"
LABEL_FONT_PX = 11
_CHAR_W = 0.64  # width of a bold label character, in font sizes (a generous estimate)


def esc(text) -> str:
    """HTML-escape ``text`` for element content and quoted attributes."""
    return html.escape(str(text), quote=True)


def rgb_css(rgb) -> str:
    return "rgb({},{},{})".format(*(int(v) for v in rgb))


def png_data_uri(rgb: np.ndarray) -> str:
    """``data:image/png;base64,...`` of an (H, W, 3) RGB or (H, W) uint8 image."""
    import cv2

    img = np.ascontiguousarray(rgb[:, :, ::-1]) if rgb.ndim == 3 else np.ascontiguousarray(rgb)
    ok, buf = cv2.imencode(".png", img)
    if not ok:  # pragma: no cover - OpenCV always encodes uint8
        raise OSError("could not encode a report picture")
    return "data:image/png;base64," + base64.b64encode(buf.tobytes()).decode("ascii")


def jpeg_data_uri(rgb: np.ndarray, *, quality: int = 90) -> str:
    """``data:image/jpeg;base64,...`` of an (H, W, 3) RGB image (for photo-like renders)."""
    import cv2

    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(rgb[:, :, ::-1]),
                           [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:  # pragma: no cover
        raise OSError("could not encode a report picture")
    return "data:image/jpeg;base64," + base64.b64encode(buf.tobytes()).decode("ascii")


def resize(rgb: np.ndarray, scale: float) -> np.ndarray:
    """``rgb`` scaled by ``scale`` (area averaging down, nearest neighbour up)."""
    import cv2

    if scale == 1.0:
        return rgb
    h, w = rgb.shape[:2]
    return cv2.resize(rgb, (max(1, round(w * scale)), max(1, round(h * scale))),
                      interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_NEAREST)


# --------------------------------------------------------------------------- colours


def _cmap_rgb(t: np.ndarray) -> np.ndarray:
    import matplotlib

    return (matplotlib.colormaps[CMAP](np.clip(t, 0.0, 1.0))[..., :3] * 255).astype(np.uint8)


def colourise(height_mm: np.ndarray, reliable: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """(H, W, 3) uint8 picture of heights on [lo, hi] (clipped); unreliable pixels dimmed."""
    h = np.where(np.isfinite(height_mm), height_mm, lo)
    rgb = _cmap_rgb((h - lo) / max(hi - lo, 1e-9))
    bad = ~np.asarray(reliable, bool)
    rgb[bad] = (rgb[bad] * 0.25 + 40).astype(np.uint8)
    return rgb


def height_range(values: np.ndarray, *, lo_pct: float = 0.5, hi_pct: float = 99.8,
                 min_span_mm: float = 1e-3) -> tuple[float, float]:
    """A robust (lo, hi) of finite ``values`` (percentiles), at least ``min_span_mm`` wide."""
    v = np.asarray(values, np.float64)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return 0.0, max(min_span_mm, 1e-3)
    lo, hi = float(np.percentile(v, lo_pct)), float(np.percentile(v, hi_pct))
    if hi - lo < min_span_mm:
        mid = 0.5 * (lo + hi)
        lo, hi = mid - min_span_mm / 2, mid + min_span_mm / 2
    return lo, hi


def nice_ticks(lo: float, hi: float, n: int = 5) -> list[float]:
    """Round tick values (1, 2 or 5 × 10^k apart) inside [lo, hi], about ``n`` of them."""
    if not (math.isfinite(lo) and math.isfinite(hi)) or hi <= lo:
        return [lo] if math.isfinite(lo) else []
    raw = (hi - lo) / max(n - 1, 1)
    mag = 10 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1, 2, 5, 10) if m * mag >= raw * 0.999)
    first = math.ceil(lo / step - 1e-9) * step
    ticks = []
    t = first
    while t <= hi + 1e-9 * step:
        ticks.append(0.0 if abs(t) < step * 1e-6 else round(t, 12))
        t += step
    return ticks


def nice_length(x: float) -> float:
    """The largest 1, 2 or 5 × 10^k not above ``x`` (``x`` > 0)."""
    mag = 10 ** math.floor(math.log10(x))
    for m in (5, 2, 1):
        if m * mag <= x * 1.000001:
            return m * mag
    return mag  # pragma: no cover


def _tick_text(v: float, step: float) -> str:
    nd = max(0, -math.floor(math.log10(step) + 1e-9)) if step > 0 else 2
    return f"{v:.{nd}f}"


def colour_bar_svg(lo: float, hi: float, *, height_px: int, label: str = "height mm",
                   band: tuple[float, float] | None = None, width_px: int = 74,
                   uid: str = "cb") -> str:
    """A vertical colour bar of :data:`CMAP` from ``lo`` (bottom) to ``hi`` (top), in mm.

    ``band``: an acceptance band (min, max) drawn as a bracket beside the bar; ``uid``
    names the gradient (unique in the page).
    """
    top, bottom, bar_x, bar_w = 16, 8, 14, 14
    h_bar = max(20, height_px - top - bottom)
    stops = "".join(
        f"<stop offset='{i / 10:.1f}' stop-color='{rgb_css(_cmap_rgb(np.array([1 - i / 10]))[0])}'/>"
        for i in range(11))
    gid = esc(uid)
    y_of = lambda v: top + (hi - v) / (hi - lo) * h_bar  # noqa: E731
    ticks = nice_ticks(lo, hi, max(3, h_bar // 40))
    step = ticks[1] - ticks[0] if len(ticks) > 1 else hi - lo
    parts = [f"<svg class='colourbar' width='{width_px}' height='{height_px}' "
             f"viewBox='0 0 {width_px} {height_px}' role='img' aria-label='{esc(label)} colour bar'>",
             f"<defs><linearGradient id='{gid}' x1='0' y1='0' x2='0' y2='1'>{stops}"
             "</linearGradient></defs>",
             f"<text x='2' y='11' class='cbl'>{esc(label)}</text>",
             f"<rect x='{bar_x}' y='{top}' width='{bar_w}' height='{h_bar}' fill='url(#{gid})' "
             "stroke='#555' stroke-width='0.5'/>"]
    for t in ticks:
        y = y_of(t)
        parts.append(f"<line x1='{bar_x + bar_w}' x2='{bar_x + bar_w + 4}' y1='{y:.1f}' y2='{y:.1f}' "
                     "stroke='#333'/>"
                     f"<text x='{bar_x + bar_w + 6}' y='{y + 3.5:.1f}' class='tick'>"
                     f"{esc(_tick_text(t, step))}</text>")
    if band is not None and all(math.isfinite(b) for b in band):
        b0, b1 = (min(max(v, lo), hi) for v in band)
        y0, y1 = y_of(b1), y_of(b0)
        x = bar_x - 4
        parts.append(f"<path d='M{x + 3},{y0:.1f} H{x} V{y1:.1f} H{x + 3}' fill='none' "
                     "stroke='#2e7d32' stroke-width='2'><title>acceptance band "
                     f"{esc(f'{band[0]:.3f}–{band[1]:.3f} mm')}</title></path>")
    parts.append("</svg>")
    return "".join(parts)


# --------------------------------------------------------------------------- overview


@dataclass(frozen=True)
class PadMark:
    """One joint as drawn on the overview: outline (display px), label, colour, link."""

    polygon: np.ndarray  # (N, 2) display px
    label: str
    colour: tuple[int, int, int]
    href: str
    tooltip: str
    outward: tuple[float, float]  # unit vector (display px) away from the component


def _text_colour(rgb) -> str:
    r, g, b = rgb
    return "#000" if 0.299 * r + 0.587 * g + 0.114 * b > 140 else "#fff"


def _overlap(a, b) -> float:
    w = min(a[2], b[2]) - max(a[0], b[0])
    h = min(a[3], b[3]) - max(a[1], b[1])
    return w * h if w > 0 and h > 0 else 0.0


def place_labels(marks: list[PadMark], *, size: tuple[int, int],
                 font_px: int = LABEL_FONT_PX) -> list[tuple[float, float, float, float]]:
    """Label boxes (x0, y0, x1, y1) in display px, one per mark, placed greedily.

    Candidates sit just outside the pad's bounding box, first in the pad's outward
    direction, then turning round it, then further away; the first mark placed gets
    the best spot, so callers list the marks that matter most (defects) first. The
    score penalises overlap with placed labels most, then with other pads, leaving the
    picture, and distance.
    """
    W, H = size
    pads = [(float(m.polygon[:, 0].min()), float(m.polygon[:, 1].min()),
             float(m.polygon[:, 0].max()), float(m.polygon[:, 1].max())) for m in marks]
    placed: list[tuple[float, float, float, float]] = []
    for k, m in enumerate(marks):
        w = _CHAR_W * font_px * len(m.label) + 6
        h = font_px + 4
        x0, y0, x1, y1 = pads[k]
        cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
        hx, hy = (x1 - x0) / 2, (y1 - y0) / 2
        ux, uy = m.outward
        best, best_score = None, math.inf
        for ring, gap in enumerate((2.0, 8.0, 18.0, 32.0)):
            for turn, ang in enumerate((0, 45, -45, 90, -90, 135, -135, 180)):
                a = math.radians(ang)
                dx, dy = ux * math.cos(a) - uy * math.sin(a), ux * math.sin(a) + uy * math.cos(a)
                t = min(hx / abs(dx) if abs(dx) > 1e-9 else math.inf,
                        hy / abs(dy) if abs(dy) > 1e-9 else math.inf)
                reach = gap + abs(dx) * w / 2 + abs(dy) * h / 2
                lx, ly = cx + dx * (t + reach), cy + dy * (t + reach)
                box = (lx - w / 2, ly - h / 2, lx + w / 2, ly + h / 2)
                area = w * h
                score = sum(_overlap(box, p) for p in placed) / area * 1000
                score += sum(_overlap(box, p) for i, p in enumerate(pads) if i != k) / area * 150
                score += _overlap(box, pads[k]) / area * 60
                inside = _overlap(box, (0, 0, W, H)) / area
                score += (1 - inside) * 500 + ring * 6 + turn * 0.8
                if score < best_score:
                    best, best_score = box, score
        placed.append(best)
    return placed


def overview_svg(rgb: np.ndarray, marks: list[PadMark], *, labels: bool = True,
                 css_class: str = "overview", extra: str = "", aria: str = "board") -> str:
    """The board picture ``rgb`` (display size) with every pad outlined and labelled.

    Each label is a chip in the verdict's colour that links to the joint's entry;
    ``extra`` is SVG drawn on top (e.g. a rejected board outline).
    """
    H, W = rgb.shape[:2]
    parts = [f"<svg class='{css_class}' width='{W}' height='{H}' viewBox='0 0 {W} {H}' "
             f"role='img' aria-label='{esc(aria)}'>",
             f"<image href='{png_data_uri(rgb)}' x='0' y='0' width='{W}' height='{H}'/>"]
    for m in marks:
        pts = " ".join(f"{x:.1f},{y:.1f}" for x, y in m.polygon)
        parts.append(f"<polygon points='{pts}' fill='none' stroke='{rgb_css(m.colour)}' "
                     f"stroke-width='{2 if labels else 1.2}'><title>{esc(m.tooltip)}</title></polygon>")
    if labels and marks:
        boxes = place_labels(marks, size=(W, H))
        leaders, chips = [], []
        for m, (x0, y0, x1, y1) in zip(marks, boxes):
            px0, py0 = m.polygon[:, 0].min(), m.polygon[:, 1].min()
            px1, py1 = m.polygon[:, 0].max(), m.polygon[:, 1].max()
            # Leader from the pad's box to the label's box when they do not touch.
            ax, ay = min(max((x0 + x1) / 2, px0), px1), min(max((y0 + y1) / 2, py0), py1)
            bx, by = min(max(ax, x0), x1), min(max(ay, y0), y1)
            if math.hypot(bx - ax, by - ay) > 3:
                leaders.append(f"<line x1='{ax:.1f}' y1='{ay:.1f}' x2='{bx:.1f}' y2='{by:.1f}' "
                               f"stroke='{rgb_css(m.colour)}' stroke-width='1.5'/>")
            chips.append(
                f"<a href='{esc(m.href)}' class='jl' data-joint='{esc(m.label)}'>"
                f"<title>{esc(m.tooltip)}</title>"
                f"<rect x='{x0:.1f}' y='{y0:.1f}' width='{x1 - x0:.1f}' height='{y1 - y0:.1f}' rx='3' "
                f"fill='{rgb_css(m.colour)}' stroke='#fff' stroke-width='0.8'/>"
                f"<text x='{(x0 + x1) / 2:.1f}' y='{y1 - 4:.1f}' text-anchor='middle' "
                f"fill='{_text_colour(m.colour)}'>{esc(m.label)}</text></a>")
        parts.append("<g class='leaders'>" + "".join(leaders) + "</g>")
        parts.append("<g class='labels'>" + "".join(chips) + "</g>")
    parts.append(extra)
    parts.append("</svg>")
    return "".join(parts)


# --------------------------------------------------------------------------- profiles


def joint_profile(height_mm: np.ndarray, reliable: np.ndarray, start_px, end_px, *,
                  pixel_size_mm: float, strip_px: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Heights along the segment ``start_px`` → ``end_px`` ((col, row) pixels).

    One sample per pixel of length; each is the median of the reliable pixels of a
    strip ``strip_px`` wide across the segment (NaN where none is reliable).

    Returns
    -------
    s_mm : (n,) float64
        Distance from ``start_px`` in mm.
    z_mm : (n,) float64
        Height (the map's units, mm); NaN where nothing reliable was measured.
    """
    p0, p1 = np.asarray(start_px, np.float64), np.asarray(end_px, np.float64)
    length = float(np.hypot(*(p1 - p0)))
    n = max(2, int(math.ceil(length)) + 1)
    t = np.linspace(0.0, 1.0, n)
    along = (p1 - p0) / max(length, 1e-9)
    across = np.array([-along[1], along[0]])
    H, W = height_mm.shape
    offs = np.arange(strip_px) - (strip_px - 1) / 2
    pts = p0[None, None, :] + t[:, None, None] * (p1 - p0) + offs[None, :, None] * across
    cols = np.clip(np.round(pts[..., 0]).astype(int), 0, W - 1)
    rows = np.clip(np.round(pts[..., 1]).astype(int), 0, H - 1)
    inside = (pts[..., 0] > -0.5) & (pts[..., 0] < W - 0.5) & (pts[..., 1] > -0.5) & (pts[..., 1] < H - 0.5)
    vals = np.where(inside & reliable[rows, cols] & np.isfinite(height_mm[rows, cols]),
                    height_mm[rows, cols], np.nan).astype(np.float64)
    with np.errstate(all="ignore"):
        z = np.full(n, np.nan)
        has = np.isfinite(vals).any(axis=1)
        z[has] = np.nanmedian(vals[has], axis=1)
    return t * length * pixel_size_mm, z


def profile_svg(s_mm: np.ndarray, z_mm: np.ndarray, *, pad_mm: tuple[float, float],
                band_mm: tuple[float, float], nominal_mm: float, measured_mm: float,
                uncertainty_mm: float, colour, uid: str, ends: tuple[str, str] = ("A", "B"),
                extra_marks: list[tuple[str, float]] = (), size: tuple[int, int] = (360, 220)) -> str:
    """A height profile against the joint's acceptance band, as SVG.

    ``s_mm`` runs from end ``A`` to end ``B`` of the profile line; ``pad_mm`` is the
    pad's extent along it, over which the band [min, max] is shaded, the nominal height
    dashed and the measured max (± its uncertainty) drawn in the verdict colour.
    Heights beyond the plotted range (a body top well above the band and the marks)
    are clipped;
    ``extra_marks`` are further labelled horizontal lines (e.g. a gap height).
    """
    W, H = size
    ml, mr, mt, mb = 44, 12, 18, 34
    pw, ph = W - ml - mr, H - mt - mb
    s = np.asarray(s_mm, np.float64)
    z = np.asarray(z_mm, np.float64)
    s0, s1 = float(s[0]), float(s[-1]) if s[-1] > s[0] else float(s[0]) + 1.0
    near = (s >= pad_mm[0] - 0.15) & (s <= pad_mm[1] + 0.15) & np.isfinite(z)
    cand = [band_mm[1], nominal_mm, 0.0]
    if math.isfinite(measured_mm):
        cand.append(measured_mm + (uncertainty_mm if math.isfinite(uncertainty_mm) else 0))
    cand += [v for _, v in extra_marks if math.isfinite(v)]
    hi = max(c for c in cand if math.isfinite(c))
    # The measured heights over the pad widen the range, up to 1.5 x the band's and
    # the marks' top: a body top next to a fillet is clipped rather than squash it.
    if near.any():
        hi = max(hi, min(float(np.max(z[near])), 1.5 * hi))
    lo = min(0.0, float(np.nanmin(z)) if np.isfinite(z).any() else 0.0,
             measured_mm if math.isfinite(measured_mm) else 0.0)
    span = max(hi - lo, 0.05)
    lo, hi = lo - 0.06 * span, hi + 0.12 * span
    clipped = bool(np.isfinite(z).any() and np.nanmax(z) > hi)

    def X(v):
        return ml + (v - s0) / (s1 - s0) * pw

    def Y(v):
        return mt + (hi - v) / (hi - lo) * ph

    c = rgb_css(colour)
    out = [f"<svg class='profile' width='{W}' height='{H}' viewBox='0 0 {W} {H}' role='img' "
           f"aria-label='height profile'>",
           f"<defs><clipPath id='{esc(uid)}'><rect x='{ml}' y='{mt}' width='{pw}' height='{ph}'/>"
           "</clipPath></defs>",
           f"<rect x='{ml}' y='{mt}' width='{pw}' height='{ph}' fill='#fff' stroke='#999'/>"]
    # Axes ticks.
    yt = nice_ticks(lo, hi, 5)
    ystep = yt[1] - yt[0] if len(yt) > 1 else 0.1
    for v in yt:
        out.append(f"<line x1='{ml}' x2='{ml + pw}' y1='{Y(v):.1f}' y2='{Y(v):.1f}' stroke='#eee'/>"
                   f"<text x='{ml - 4}' y='{Y(v) + 3.5:.1f}' text-anchor='end' class='tick'>"
                   f"{esc(_tick_text(v, ystep))}</text>")
    xt = nice_ticks(s0, s1, 6)
    xstep = xt[1] - xt[0] if len(xt) > 1 else 0.1
    for v in xt:
        out.append(f"<line x1='{X(v):.1f}' x2='{X(v):.1f}' y1='{mt + ph}' y2='{mt + ph + 4}' stroke='#333'/>"
                   f"<text x='{X(v):.1f}' y='{mt + ph + 14}' text-anchor='middle' class='tick'>"
                   f"{esc(_tick_text(v, xstep))}</text>")
    out.append(f"<text x='{ml + pw / 2}' y='{H - 4}' text-anchor='middle' class='axl'>"
               f"distance along the profile, mm</text>"
               f"<text x='{ml + 3}' y='{mt + ph + 28}' class='axl' font-weight='bold'>{esc(ends[0])}</text>"
               f"<text x='{ml + pw - 3}' y='{mt + ph + 28}' text-anchor='end' class='axl' "
               f"font-weight='bold'>{esc(ends[1])}</text>"
               f"<text x='4' y='{mt - 7}' class='axl'>height mm</text>")
    # Pad extent, band, nominal.
    xa, xb = X(max(pad_mm[0], s0)), X(min(pad_mm[1], s1))
    out.append(f"<g clip-path='url(#{esc(uid)})'>")
    out.append(f"<rect x='{xa:.1f}' y='{mt}' width='{xb - xa:.1f}' height='{ph}' fill='#f4f4f4'/>")
    ya, yb = Y(band_mm[1]), Y(band_mm[0])
    out.append(f"<rect x='{xa:.1f}' y='{ya:.1f}' width='{xb - xa:.1f}' height='{yb - ya:.1f}' "
               "fill='rgba(46,160,67,0.18)' stroke='#2e7d32' stroke-dasharray='4 2'>"
               f"<title>acceptance band {band_mm[0]:.3f}–{band_mm[1]:.3f} mm</title></rect>")
    out.append(f"<line x1='{xa:.1f}' x2='{xb:.1f}' y1='{Y(nominal_mm):.1f}' y2='{Y(nominal_mm):.1f}' "
               "stroke='#2e7d32' stroke-dasharray='2 3'/>")
    out.append(f"<line x1='{ml}' x2='{ml + pw}' y1='{Y(0):.1f}' y2='{Y(0):.1f}' stroke='#888' "
               "stroke-width='0.8'/>")
    # The measured profile, broken where nothing reliable was measured.
    ok = np.isfinite(z)
    runs, cur = [], []
    for k in range(len(s)):
        if ok[k]:
            cur.append(f"{X(s[k]):.1f},{Y(z[k]):.1f}")
        elif cur:
            runs.append(cur)
            cur = []
    if cur:
        runs.append(cur)
    for r in runs:
        if len(r) == 1:
            x, y = r[0].split(",")
            out.append(f"<circle cx='{x}' cy='{y}' r='1.6' fill='#222'/>")
        else:
            out.append(f"<polyline points='{' '.join(r)}' fill='none' stroke='#222' stroke-width='1.6'/>")
    if math.isfinite(measured_mm):
        ym = Y(measured_mm)
        if math.isfinite(uncertainty_mm) and uncertainty_mm > 0:
            u0, u1 = Y(measured_mm + uncertainty_mm), Y(measured_mm - uncertainty_mm)
            out.append(f"<rect x='{xa:.1f}' y='{u0:.1f}' width='{xb - xa:.1f}' height='{max(u1 - u0, 0.5):.1f}' "
                       f"fill='{c}' opacity='0.25'/>")
        out.append(f"<line x1='{xa:.1f}' x2='{xb:.1f}' y1='{ym:.1f}' y2='{ym:.1f}' stroke='{c}' "
                   "stroke-width='2'/>")
    for name, v in extra_marks:
        if math.isfinite(v):
            out.append(f"<line x1='{ml}' x2='{ml + pw}' y1='{Y(v):.1f}' y2='{Y(v):.1f}' stroke='{c}' "
                       f"stroke-dasharray='6 3'><title>{esc(name)}</title></line>")
    out.append("</g>")
    # Labels on the right of the pad zone (outside the clip so they stay readable).
    notes = []
    if math.isfinite(measured_mm):
        notes.append((Y(measured_mm), f"max {measured_mm:.3f}", c))
    notes.append((Y(band_mm[1]), f"band {band_mm[1]:.3f}", "#2e7d32"))
    notes.append((Y(band_mm[0]), f"band {band_mm[0]:.3f}", "#2e7d32"))
    notes += [(Y(v), f"{name} {v:.3f}", c) for name, v in extra_marks if math.isfinite(v)]
    # Spread the notes so they do not overprint each other.
    notes.sort(key=lambda n: n[0])
    last = -math.inf
    lx = min(xb + 3, ml + pw - 2)
    anchor = "start" if xb + 70 < ml + pw else "end"
    if anchor == "end":
        lx = xa - 3 if xa - 70 > ml else ml + pw - 2
    for y, text, col in notes:
        y = min(max(y, mt + 8), mt + ph - 2)
        y = max(y, last + 10)
        last = y
        out.append(f"<text x='{lx:.1f}' y='{y + 3:.1f}' text-anchor='{anchor}' class='note' "
                   f"fill='{col}'>{esc(text)}</text>")
    out.append(f"<text x='{(xa + xb) / 2:.1f}' y='{mt + 10}' text-anchor='middle' class='note' "
               "fill='#777'>pad</text>")
    if not ok.any():
        out.append(f"<text x='{ml + pw / 2}' y='{mt + ph / 2}' text-anchor='middle' class='axl' "
                   "fill='#c62828'>no reliable pixel along this profile</text>")
    if clipped:
        out.append(f"<text x='{ml + pw - 3}' y='{mt + 10}' text-anchor='end' class='note' "
                   f"fill='#777'>clipped above {hi:.2f}</text>")
    out.append("</svg>")
    return "".join(out)


# --------------------------------------------------------------------------- crops


def crop_svg(rgb: np.ndarray, box: tuple[int, int, int, int], *, polygon_px: np.ndarray,
             line_px: tuple[np.ndarray, np.ndarray] | None, pixel_size_mm: float, title: str,
             outline: tuple[int, int, int] = (255, 255, 255), ends: tuple[str, str] = ("A", "B"),
             fit_px: tuple[int, int] = (300, 250)) -> str:
    """A crop ``box`` = (c0, r0, c1, r1) (pixels, end exclusive) of ``rgb`` as SVG.

    Drawn with the pad outline, the profile line (A → B), a scale bar and ``title``.
    Scaled to fit ``fit_px`` (width, height); enlarged with nearest neighbour (pixels
    stay visible), by a whole factor where that shrinks the picture by at most 20 %.
    """
    c0, r0, c1, r1 = box
    sub = rgb[r0:r1, c0:c1]
    h, w = sub.shape[:2]
    s = min(fit_px[0] / w, fit_px[1] / h)
    if s >= 2 and math.floor(s) / s >= 0.8:  # whole factors when that costs little size
        s = float(math.floor(s))
    sub = resize(sub, s)
    h_d, w_d = sub.shape[:2]
    s_x, s_y = w_d / w, h_d / h

    def P(pt):
        return (pt[0] - c0 + 0.5) * s_x, (pt[1] - r0 + 0.5) * s_y

    top = 16
    Ht = h_d + top
    parts = [f"<svg class='crop' width='{w_d}' height='{Ht}' viewBox='0 0 {w_d} {Ht}' role='img' "
             f"aria-label='{esc(title)}'>",
             f"<text x='1' y='12' class='panel'>{esc(title)}</text>",
             f"<g transform='translate(0,{top})'>",
             f"<image href='{png_data_uri(sub)}' x='0' y='0' width='{w_d}' height='{h_d}'/>"]
    pts = " ".join("{:.1f},{:.1f}".format(*P(p)) for p in np.asarray(polygon_px))
    parts.append(f"<polygon points='{pts}' fill='none' stroke='{rgb_css(outline)}' stroke-width='1.5'/>")
    if line_px is not None:
        (ax, ay), (bx, by) = P(line_px[0]), P(line_px[1])
        parts.append(f"<line x1='{ax:.1f}' y1='{ay:.1f}' x2='{bx:.1f}' y2='{by:.1f}' stroke='#000' "
                     "stroke-width='3' opacity='0.6'/>"
                     f"<line x1='{ax:.1f}' y1='{ay:.1f}' x2='{bx:.1f}' y2='{by:.1f}' stroke='#fff' "
                     "stroke-width='1.2' stroke-dasharray='4 3'/>")
        for (x, y), name in (((ax, ay), ends[0]), ((bx, by), ends[1])):
            x = min(max(x, 7), w_d - 7)
            y = min(max(y, 7), h_d - 7)
            parts.append(f"<circle cx='{x:.1f}' cy='{y:.1f}' r='6.5' fill='#fff' stroke='#000'/>"
                         f"<text x='{x:.1f}' y='{y + 3.5:.1f}' text-anchor='middle' class='end'>"
                         f"{esc(name)}</text>")
    # Scale bar: a round length of about a quarter of the crop.
    width_mm = w * pixel_size_mm
    bar_mm = nice_length(0.28 * width_mm)
    bar_px = bar_mm / pixel_size_mm * s_x
    x0, y0 = 6, h_d - 7
    label = f"{bar_mm * 1000:g} µm" if bar_mm < 1 else f"{bar_mm:g} mm"
    text_px = 6.2 * len(label)
    parts.append(f"<rect x='{x0 - 4}' y='{y0 - 16}' width='{max(bar_px, text_px) + 8:.1f}' "
                 "height='21' rx='2' fill='#000' opacity='0.6'/>"
                 f"<line x1='{x0}' x2='{x0 + bar_px:.1f}' y1='{y0}' y2='{y0}' stroke='#fff' "
                 "stroke-width='3'/>"
                 f"<text x='{x0}' y='{y0 - 5}' class='sb'>{esc(label)}</text>")
    parts.append("</g></svg>")
    return "".join(parts)
