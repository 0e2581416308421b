"""``height.png``: the colour-mapped height map with a legend in mm and a scale bar.

Drawn with OpenCV only (colour map, resizing, lines, text): no matplotlib, whose import
and figure cost more than the rest of the picture. Colours are viridis (OpenCV's
``COLORMAP_VIRIDIS``); unreliable pixels show the all-in-focus image as a pale grey
under the colours, so they are marked without taking the eye.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["display_range", "render_height_map"]

MAP_MAX_SIDE = 1600  # larger maps are downsized (block means) to this long side
MAP_MIN_SIDE = 1000  # smaller maps are enlarged by a whole factor (nearest) to at least this
UNRELIABLE_GREY = 0.78  # mean level of the unreliable pixels (0..1)
UNRELIABLE_TEXTURE = 0.22  # how much of the all-in-focus image shows through them
INK = (38, 30, 30)  # BGR
FONT = 0  # cv2.FONT_HERSHEY_SIMPLEX


def _lut_bgr() -> np.ndarray:
    import cv2

    return cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None], cv2.COLORMAP_VIRIDIS)[:, 0]


def display_range(height_mm: np.ndarray, reliable: np.ndarray) -> tuple[float, float]:
    """The colour range: 0.5 and 99.5 percentiles of the reliable heights (of all
    heights when fewer than 10 are reliable), at least 1 µm wide."""
    vals = height_mm[reliable]
    vals = vals[np.isfinite(vals)]
    if vals.size < 10:
        vals = height_mm[np.isfinite(height_mm)]
    if vals.size == 0:
        return 0.0, 1e-3
    lo, hi = np.percentile(vals, [0.5, 99.5])
    if hi - lo < 1e-6:
        hi = lo + 1e-3
    return float(lo), float(hi)


def render_height_map(
    height_mm: np.ndarray,
    reliable: np.ndarray,
    *,
    aif: np.ndarray | None = None,
    pixel_size_mm: float | None = None,
    value_range: tuple[float, float] | None = None,
) -> np.ndarray:
    """The ``height.png`` picture as an RGB array.

    Parameters
    ----------
    height_mm : (H, W) float
        Heights in mm.
    reliable : (H, W) bool
        Pixels whose height is measured; the others are drawn pale grey (textured with
        ``aif`` when given) and their share is written on the picture.
    aif : (H, W) or (H, W, 3) uint8, uint16 or float in [0, 1], optional
        All-in-focus image shown faintly under the unreliable pixels.
    pixel_size_mm : float or None
        Object-side pixel size; the scale bar is in mm, in pixels when None.
    value_range : (lo, hi), optional
        Heights mapped to the ends of the colour map (default :func:`display_range`).

    Returns
    -------
    (H', W', 3) uint8
        RGB; the map is resized so its long side is between 1000 and 1600 px, with the
        title above it and the colour bar (ticks in mm) on its right.
    """
    import cv2

    height = np.asarray(height_mm, dtype=np.float32)
    ok = np.asarray(reliable, dtype=bool) & np.isfinite(height)
    lo, hi = display_range(height, ok) if value_range is None else map(float, value_range)
    h, w = height.shape
    side = max(h, w)
    if side > MAP_MAX_SIDE:
        scale = MAP_MAX_SIDE / side
    else:
        scale = float(max(1, math.ceil(MAP_MIN_SIDE / side)))
    mw, mh = max(1, round(w * scale)), max(1, round(h * scale))

    # heights and the reliable share of every drawn pixel (block means when downsized)
    okf = ok.view(np.uint8).astype(np.float32)
    hv = np.where(ok, height, np.float32(0.0))
    if scale < 1:
        weight = cv2.resize(okf, (mw, mh), interpolation=cv2.INTER_AREA)
        hv = cv2.resize(hv, (mw, mh), interpolation=cv2.INTER_AREA)
        hv = np.divide(hv, weight, out=np.zeros_like(hv), where=weight > 1e-6)
    else:
        weight = okf
    bg = _background(aif, (h, w), None if scale >= 1 else (mw, mh))
    lut = _lut_bgr()
    colour = lut[_lut_index(hv, lo, hi)]
    picture = cv2.blendLinear(colour, bg, weight, 1.0 - weight)
    if scale > 1:
        picture = cv2.resize(picture, (mw, mh), interpolation=cv2.INTER_NEAREST)

    return _compose(picture, lut, lo, hi, coverage=float(ok.mean()), scale=scale,
                    pixel_size_mm=pixel_size_mm, width_px=w)[:, :, ::-1]


def _lut_index(height: np.ndarray, lo: float, hi: float) -> np.ndarray:
    t = (height - np.float32(lo)) * np.float32(255.0 / (hi - lo)) + np.float32(0.5)
    return np.clip(t, 0, 255).astype(np.uint8)


def _background(aif, shape, size) -> np.ndarray:
    """Pale grey (BGR uint8) for the unreliable pixels, with a trace of the all-in-focus
    image; ``size`` (width, height) when the map is downsized."""
    import cv2

    h, w = shape
    img = None if aif is None else np.asarray(aif)
    if img is None or img.shape[:2] != (h, w):
        grey = np.full((h, w) if size is None else size[::-1], UNRELIABLE_GREY * 255, np.float32)
    else:
        if img.dtype == np.uint8:
            unit = 255.0
        elif img.dtype == np.uint16:
            unit = 65535.0
        else:
            img = np.clip(np.nan_to_num(img.astype(np.float32)), 0.0, 1.0)
            unit = 1.0
        if img.ndim == 3:
            img = cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2GRAY)
        if size is not None:
            img = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
        gain = UNRELIABLE_TEXTURE * 255.0 / unit
        mean = float(cv2.mean(img)[0])
        grey = img.astype(np.float32) * np.float32(gain) \
            + np.float32(UNRELIABLE_GREY * 255.0 - gain * mean)
    return cv2.cvtColor(np.clip(grey, 0, 255).astype(np.uint8), cv2.COLOR_GRAY2BGR)


def _nice_step(span: float, target: int = 6) -> float:
    """A round tick step (1, 2, 2.5, 5 × 10^k) giving about ``target`` ticks over ``span``."""
    raw = span / target
    e = 10.0 ** math.floor(math.log10(raw))
    for m in (1.0, 2.0, 2.5, 5.0, 10.0):
        if m * e >= raw * (1 - 1e-9):
            return m * e
    return 10.0 * e


def _nice_length(x: float) -> float:
    """The largest of 1, 2, 5 × 10^k not above ``x``."""
    e = 10.0 ** math.floor(math.log10(x) + 1e-9)
    for m in (5.0, 2.0, 1.0):
        if m * e <= x * (1 + 1e-9):
            return m * e
    return e


def _ticks(lo: float, hi: float) -> tuple[np.ndarray, int]:
    step = _nice_step(hi - lo)
    ticks = np.arange(math.ceil(lo / step - 1e-9), math.floor(hi / step + 1e-9) + 1) * step
    decimals = max(0, -math.floor(math.log10(step) + 1e-9))
    if round(step / 10.0 ** -decimals, 6) % 1:  # 2.5 x 10^k needs one more digit
        decimals += 1
    return ticks, decimals


def _compose(picture, lut, lo, hi, *, coverage, scale, pixel_size_mm, width_px) -> np.ndarray:
    """The map with its title, colour bar, scale bar and notes; BGR."""
    import cv2

    mh, mw = picture.shape[:2]
    fs = max(mw, mh) / 1250.0  # font scale: text about 2 % of the map's long side
    th = max(1, round(2 * fs))  # stroke
    text_h = cv2.getTextSize("0", FONT, fs, th)[0][1]
    pad = round(1.2 * text_h)
    ticks, decimals = _ticks(lo, hi)
    labels = [f"{t + 0.0:.{decimals}f}" for t in ticks]  # + 0.0: no "-0.0"
    label_w = max(cv2.getTextSize(s, FONT, fs, th)[0][0] for s in labels + ["mm"])
    bar_w = max(16, round(0.035 * max(mw, mh)))
    tick_len = round(0.4 * bar_w)
    # the title over the map (one line, two when the map is narrow), with a swatch for
    # the unreliable pixels; the colour bar's unit over the bar
    title = "height above board (mm)"
    note = f"unreliable: {100 * (1 - coverage):.1f} %"
    gap = 2 * text_h
    title_w = cv2.getTextSize(title, FONT, fs, th)[0][0]
    note_w = round(1.6 * text_h) + cv2.getTextSize(note, FONT, fs, th)[0][0]
    widths = {title: title_w, note: note_w}
    lines = [[title, note]] if title_w + gap + note_w <= mw else [[title], [note]]
    x0 = pad + mw + pad  # the colour bar's left edge
    width = max(x0 + bar_w + tick_len + round(0.5 * text_h) + label_w,
                max(title_w, note_w)) + pad
    feet = ["colours: 0.5 to 99.5 percentile of the reliable heights, clipped"]
    if not pixel_size_mm:
        feet.insert(0, "pixel size unknown: x, y in pixels")
    ffs, fth = 0.75 * fs, max(1, th - 1)
    one_line = ";  ".join(feet)
    if len(feet) == 2 and cv2.getTextSize(one_line, FONT, ffs, fth)[0][0] <= width - 2 * pad:
        feet = [one_line]
    line_h = round(1.9 * text_h)
    unit_line = pad + sum(widths[p] for p in lines[-1]) + gap * (len(lines[-1]) - 1) > x0 - text_h
    top = round(1.3 * text_h) + line_h * (len(lines) + unit_line)
    bottom = round(1.0 * text_h) + round(1.6 * text_h) * len(feet)
    canvas = np.full((top + mh + bottom, width, 3), 255, np.uint8)  # white paper
    canvas[top:top + mh, pad:pad + mw] = picture
    cv2.rectangle(canvas, (pad - 1, top - 1), (pad + mw, top + mh), INK, 1)
    for i, parts in enumerate(lines):
        base = round(2.1 * text_h) + i * line_h
        x = pad
        for part in parts:
            if part is note:
                grey = (int(round(UNRELIABLE_GREY * 255)),) * 3
                cv2.rectangle(canvas, (x, base - text_h), (x + text_h, base), grey, -1)
                cv2.rectangle(canvas, (x, base - text_h), (x + text_h, base), INK, 1)
                x += round(1.6 * text_h)
            _put(canvas, part, (x, base), fs, th, max_width=width - pad - x)
            x += cv2.getTextSize(part, FONT, fs, th)[0][0] + gap
    for i, foot in enumerate(feet):
        _put(canvas, foot, (pad, top + mh + round(1.8 * text_h) + round(1.6 * text_h) * i),
             ffs, fth, max_width=width - 2 * pad)

    # colour bar, top = hi, bottom = lo, ticks in mm
    rows = np.arange(mh, dtype=np.float64)
    index = np.clip(np.round((1 - rows / max(mh - 1, 1)) * 255), 0, 255).astype(np.intp)
    canvas[top:top + mh, x0:x0 + bar_w] = lut[index][:, None, :]
    cv2.rectangle(canvas, (x0 - 1, top - 1), (x0 + bar_w, top + mh), INK, 1)
    for t, s in zip(ticks, labels):
        y = top + round((hi - t) / (hi - lo) * (mh - 1))
        cv2.line(canvas, (x0 + bar_w, y), (x0 + bar_w + tick_len, y), INK, max(1, th - 1))
        _put(canvas, s, (x0 + bar_w + tick_len + round(0.5 * text_h), y + text_h // 2), fs, th)
    _put(canvas, "mm", (x0, top - round(0.6 * text_h)), fs, th)

    # scale bar on the map, bottom left, white on a dark box
    if pixel_size_mm:
        length = _nice_length(width_px * pixel_size_mm / 4)
        bar_px, unit = length / pixel_size_mm * scale, f"{length:g} mm"
    else:
        length = _nice_length(width_px / 4)
        bar_px, unit = length * scale, f"{length:g} px"
    bar_px = round(bar_px)
    tw = cv2.getTextSize(unit, FONT, fs, th)[0][0]
    bx, by = pad + pad, top + mh - pad
    box = (bx - round(0.5 * text_h), by - round(2.2 * text_h),
           bx + max(bar_px, tw) + round(0.5 * text_h), by + round(0.8 * text_h))
    if box[2] < pad + mw and box[1] > top:
        region = canvas[box[1]:box[3], box[0]:box[2]]
        region[:] = (region.astype(np.float32) * 0.45).astype(np.uint8)
        t = max(2, round(0.35 * text_h))  # a filled box: exactly bar_px long (lines get caps)
        cv2.rectangle(canvas, (bx, by - t // 2), (bx + bar_px - 1, by - t // 2 + t - 1),
                      (255, 255, 255), -1)
        _put(canvas, unit, (bx, by - round(0.6 * text_h)), fs, th, colour=(255, 255, 255))

    return canvas


def _put(canvas, text, org, fs, th, *, colour=INK, max_width=None) -> None:
    import cv2

    if max_width is not None:
        w = cv2.getTextSize(text, FONT, fs, th)[0][0]
        if w > max_width:
            fs *= max_width / w
    cv2.putText(canvas, text, org, FONT, fs, colour, th, cv2.LINE_AA)
