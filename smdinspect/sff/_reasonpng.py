"""``reason.png``: where the heights are unreliable and why.

The all-in-focus image in grey, with every unreliable pixel coloured by its reason
(:data:`~smdinspect.sff._surface.UNRELIABLE_REASONS`: the first test it failed) and a
legend of the reasons with their shares of the image, largest first. Drawn with OpenCV
only, at the size and in the style of ``height.png``.
"""

from __future__ import annotations

import math

import numpy as np

from ._heightpng import FONT, MAP_MAX_SIDE, MAP_MIN_SIDE, _put
from ._surface import UNRELIABLE_REASONS, reason_shares

__all__ = ["REASON_COLOURS", "render_reason_map"]

#: RGB colour of each reason code (Okabe-Ito's colour-blind-safe set first).
REASON_COLOURS: dict[int, tuple[int, int, int]] = {
    1: (0, 0, 0),          # outside the field: black
    2: (0, 114, 178),      # below the sweep: blue
    3: (213, 94, 0),       # above the sweep: vermillion
    4: (240, 228, 66),     # over-exposed: yellow
    5: (204, 121, 167),    # misaligned: reddish purple
    6: (0, 158, 115),      # halo: bluish green
    7: (86, 180, 233),     # depth edge: sky blue
    8: (150, 100, 50),     # unsupported: brown
    9: (250, 250, 250),    # weak texture: white (blank)
    10: (150, 60, 200),    # peak shape: violet
}
#: How much of the reason's colour covers an unreliable pixel (the rest: the image).
OPACITY = 0.75


def render_reason_map(reason: np.ndarray, aif: np.ndarray | None = None) -> np.ndarray:
    """The ``reason.png`` picture as an RGB array.

    Parameters
    ----------
    reason : (H, W) uint8
        :attr:`~smdinspect.sff.Surface.reason` (0 reliable, else a code of
        :data:`~smdinspect.sff._surface.UNRELIABLE_REASONS`).
    aif : (H, W) or (H, W, 3) uint8, uint16 or float in [0, 1], optional
        All-in-focus image, shown in grey under the colours (mid grey without it).

    Returns
    -------
    (H', W', 3) uint8
        RGB; the map's long side between 1000 and 1600 px (as ``height.png``), the title
        above it and the legend below.
    """
    import cv2

    reason = np.asarray(reason, dtype=np.uint8)
    h, w = reason.shape
    side = max(h, w)
    scale = MAP_MAX_SIDE / side if side > MAP_MAX_SIDE else float(max(1, math.ceil(MAP_MIN_SIDE / side)))
    size = (max(1, round(w * scale)), max(1, round(h * scale)))
    codes = cv2.resize(reason, size, interpolation=cv2.INTER_NEAREST)
    grey = _grey(aif, (h, w), size)
    lut = np.zeros((256, 3), np.float32)
    for code, rgb in REASON_COLOURS.items():
        lut[code] = rgb[::-1]  # BGR
    cover = np.where(codes > 0, np.float32(OPACITY), np.float32(0.0))[..., None]
    picture = (lut[codes] * cover + grey[..., None] * (1 - cover)).astype(np.uint8)
    return _compose(picture, reason_shares(reason))[:, :, ::-1]


def _grey(aif, shape, size) -> np.ndarray:
    """The all-in-focus image as float32 grey (0..255) at ``size`` (width, height)."""
    import cv2

    img = None if aif is None else np.asarray(aif)
    if img is None or img.shape[:2] != shape:
        return np.full(size[::-1], 128.0, np.float32)
    if img.dtype == np.uint16:
        img = (img / 257.0).astype(np.float32)
    elif img.dtype != np.uint8:
        img = np.clip(np.nan_to_num(img.astype(np.float32)), 0.0, 1.0) * np.float32(255.0)
    if img.ndim == 3:
        img = cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2GRAY)
    interpolation = cv2.INTER_AREA if size[0] < shape[1] else cv2.INTER_NEAREST
    return cv2.resize(img, size, interpolation=interpolation).astype(np.float32)


def _compose(picture: np.ndarray, shares: dict[str, float]) -> np.ndarray:
    """The map with its title and the legend below it; BGR."""
    import cv2

    mh, mw = picture.shape[:2]
    fs = max(mw, mh) / 1250.0
    th = max(1, round(2 * fs))
    text_h = cv2.getTextSize("0", FONT, fs, th)[0][1]
    pad = round(1.2 * text_h)
    unreliable = sum(shares.values())
    title = f"why heights are unreliable ({100 * unreliable:.1f} % of the image)"
    names = {name: code for code, (name, _) in UNRELIABLE_REASONS.items()}
    items = [(names[name], f"{name.replace('_', ' ')} {_percent(share)}")
             for name, share in shares.items()]
    items.append((0, f"reliable (the image) {100 * (1 - unreliable):.1f} %"))
    swatch = text_h
    item_w = max(cv2.getTextSize(t, FONT, fs, th)[0][0] for _, t in items) + round(2.6 * text_h)
    columns = max(1, min(len(items), mw // item_w))
    rows = -(-len(items) // columns)
    line_h = round(1.9 * text_h)
    top = round(1.3 * text_h) + line_h
    bottom = round(1.2 * text_h) + line_h * rows
    width = mw + 2 * pad
    canvas = np.full((top + mh + bottom, width, 3), 255, np.uint8)
    canvas[top:top + mh, pad:pad + mw] = picture
    cv2.rectangle(canvas, (pad - 1, top - 1), (pad + mw, top + mh), (38, 30, 30), 1)
    _put(canvas, title, (pad, round(2.1 * text_h)), fs, th, max_width=width - 2 * pad)
    for k, (code, text) in enumerate(items):
        col, row = k // rows, k % rows
        x = pad + col * item_w
        base = top + mh + round(2.3 * text_h) + row * line_h
        fill = (128, 128, 128) if code == 0 else REASON_COLOURS[code][::-1]
        cv2.rectangle(canvas, (x, base - swatch), (x + swatch, base), fill, -1)
        cv2.rectangle(canvas, (x, base - swatch), (x + swatch, base), (38, 30, 30), 1)
        _put(canvas, text, (x + round(1.6 * text_h), base), fs, th)
    return canvas


def _percent(share: float) -> str:
    return "< 0.1 %" if share < 0.0005 else f"{100 * share:.1f} %"
