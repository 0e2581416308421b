"""Ground truth next to a rendered stack: height map, scene facts, PNG previews."""

from __future__ import annotations

import logging
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from .. import _atomic
from ..optics import Optics
from ._scene import Scene, shade

log = logging.getLogger(__name__)

__all__ = ["write_truth"]


def write_truth(
    root: Path,
    scene: Scene,
    *,
    z_mm: np.ndarray,
    optics: Optics,
    sensor: Any,
    seed: int,
    preview_frames: dict[float, np.ndarray] | None = None,
    previews: bool = True,
    extra: dict[str, Any] | None = None,
) -> dict[str, Path]:
    """Write ``root/``: ``height_mm.tiff`` (float32), ``height_mm.npy``, ``scene.json``
    and, with ``previews``, ``height_mm.png`` (colour map with a scale),
    ``radiance.png`` (the in-focus image) and ``frames.png`` (a few frames).

    Returns
    -------
    dict
        Name → path of every file written.
    """
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    written: dict[str, Path] = {}
    h = np.ascontiguousarray(scene.height_mm, dtype=np.float32)
    written["height_mm.tiff"] = _atomic.write_tiff(root / "height_mm.tiff", h)
    with _atomic.atomic_path(root / "height_mm.npy") as tmp:
        np.save(tmp, h)
    written["height_mm.npy"] = root / "height_mm.npy"
    lo, hi = scene.height_range_mm()
    doc = {
        "name": scene.name,
        "pixel_size_mm": scene.pixel_size_mm,
        "image_shape": list(scene.shape),
        "color": scene.is_color,
        "height_min_mm": lo,
        "height_max_mm": hi,
        "seed": seed,
        "z_mm": [float(v) for v in z_mm],
        "optics": optics.to_dict(),
        "sensor": asdict(sensor),
        "scene_meta": scene.meta,
        "files": {"height_mm": "height_mm.tiff", "height_mm_npy": "height_mm.npy"},
    }
    if extra:
        doc.update(extra)
    written["scene.json"] = _atomic.write_json(root / "scene.json", doc)
    if previews:
        try:
            written.update(_previews(root, scene, preview_frames or {}))
        except ImportError as exc:  # matplotlib missing: the data files are what matter
            log.warning("no PNG previews (%s)", exc)
    return written


def _previews(root: Path, scene: Scene, frames: dict[float, np.ndarray]) -> dict[str, Path]:
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    out: dict[str, Path] = {}
    h = scene.height_mm
    hh, ww = scene.shape
    ext = (0, ww * scene.pixel_size_mm, 0, hh * scene.pixel_size_mm)
    fig = Figure(figsize=(6.4, 5.2), dpi=110)
    ax = fig.add_subplot()
    im = ax.imshow(h, cmap="viridis", extent=ext, interpolation="nearest")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_title(f"true height: {scene.name or 'scene'}")
    fig.colorbar(im, ax=ax, label="height (mm)")
    out["height_mm.png"] = _save(fig, root / "height_mm.png")

    rad = shade(scene)
    img = np.clip(rad / max(float(np.percentile(rad, 99.5)), 1e-6), 0, 1)
    out["radiance.png"] = _atomic.write_image(root / "radiance.png",
                                              np.rint(img * 255).astype(np.uint8))
    if frames:
        n = len(frames)
        fig = Figure(figsize=(3.2 * n, 3.6), dpi=110)
        for i, (z, f) in enumerate(sorted(frames.items())):
            ax = fig.add_subplot(1, n, i + 1)
            top = 255.0 if f.dtype == np.uint8 else 65535.0
            ax.imshow(f.astype(np.float32) / top, cmap="gray" if f.ndim == 2 else None,
                      vmin=0.0, vmax=1.0, extent=ext, interpolation="nearest")
            ax.set_title(f"z = {z:.3f} mm")
            ax.set_xticks([])
            ax.set_yticks([])
        fig.tight_layout()
        out["frames.png"] = _save(fig, root / "frames.png")
    return out


def _save(fig, path: Path) -> Path:
    with _atomic.atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    return path
