"""Rig calibration: pixel size and lens distortion from a target image, focal-plane tilt
and field curvature from a flat-target sweep, z scale and direction from a step target of
known height, and the calibration file that carries them.

Calibration file (``rig.cal.json``)::

    {"schema": "smdinspect-calibration", "version": 1,
     "pixel_size": {...PixelSizeResult fields...},        # optional
     "focal_plane": {...FocalPlaneCalibration fields...},  # optional
     "z_scale": {...ZScaleCalibration fields...}}          # optional

``smdinspect reconstruct --calibration rig.cal.json`` subtracts the focal-plane
correction, then scales z, and takes the pixel size when the stack has none.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from ..errors import InputError
from ._flat import FocalPlaneCalibration, apply_calibration, calibrate_flat
from ._pixel import PixelSizeResult, TargetKind, detect_target, pixel_size_from_image
from ._zscale import ZScaleCalibration, apply_z_scale, calibrate_z_scale

__all__ = [
    "APPLIED_META_KEYS",
    "CALIBRATION_SCHEMA",
    "FocalPlaneCalibration",
    "PixelSizeResult",
    "TargetKind",
    "ZScaleCalibration",
    "apply_calibration",
    "apply_calibration_file",
    "apply_z_scale",
    "applied_calibration",
    "calibrate_flat",
    "calibrate_z_scale",
    "detect_target",
    "pixel_size_from_image",
    "read_calibration",
    "set_rig_pixel_size",
    "write_calibration",
]

CALIBRATION_SCHEMA = "smdinspect-calibration"

#: Where a corrected surface's ``meta`` records each correction applied to it (by
#: :func:`apply_calibration` and :func:`apply_z_scale`; ``summary.json`` carries them).
APPLIED_META_KEYS = {"focal_plane": "focal_plane_calibration", "z_scale": "z_scale_calibration"}


def applied_calibration(meta: dict[str, Any] | None) -> dict[str, Any] | None:
    """``{"focal_plane": {...}, "z_scale": {...}}``: the corrections a surface's ``meta``
    says were applied to it (only those present), or None when none was."""
    meta = meta or {}
    applied = {section: meta[key] for section, key in APPLIED_META_KEYS.items()
               if isinstance(meta.get(key), dict)}
    return applied or None


def read_calibration(path: str | os.PathLike) -> dict[str, Any]:
    """Read a calibration file.

    Returns
    -------
    dict
        ``{"pixel_size_mm": float or None, "focal_plane": FocalPlaneCalibration or None,
        "z_scale": ZScaleCalibration or None, "raw": the parsed JSON}``.
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(f"calibration file {str(p)!r} does not exist")
    try:
        doc = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{p}: cannot read calibration file: {exc}") from None
    except json.JSONDecodeError as exc:
        raise InputError(f"{p}: not valid JSON: {exc.msg} at line {exc.lineno}") from None
    if not isinstance(doc, dict) or doc.get("schema") != CALIBRATION_SCHEMA:
        raise InputError(f"{p}: 'schema' must be {CALIBRATION_SCHEMA!r}")
    if doc.get("version") != 1:
        raise InputError(f"{p}: 'version' must be 1; got {doc.get('version')!r}")
    pix = doc.get("pixel_size")
    pixel = None
    if pix is not None:
        pixel = pix.get("pixel_size_mm") if isinstance(pix, dict) else None
        if not isinstance(pixel, (int, float)) or pixel <= 0:
            raise InputError(f"{p}: pixel_size.pixel_size_mm must be > 0; got {pixel!r}")
    fp = doc.get("focal_plane")
    focal = FocalPlaneCalibration.from_dict(fp, source=str(p)) if fp is not None else None
    zs = doc.get("z_scale")
    if zs is not None and not isinstance(zs, dict):
        raise InputError(f"{p}: z_scale must be an object")
    zscale = ZScaleCalibration.from_dict(zs, source=str(p)) if zs is not None else None
    return {"pixel_size_mm": pixel, "focal_plane": focal, "z_scale": zscale, "raw": doc}


def write_calibration(path: str | os.PathLike, *, pixel_size: PixelSizeResult | None = None,
                      focal_plane: FocalPlaneCalibration | None = None,
                      z_scale: ZScaleCalibration | None = None) -> Path:
    """Write (or update) a calibration file atomically; other sections are kept."""
    from .._atomic import write_json

    p = Path(path)
    doc: dict[str, Any] = {"schema": CALIBRATION_SCHEMA, "version": 1}
    if p.is_file():
        doc.update(read_calibration(p)["raw"])
    if pixel_size is not None:
        doc["pixel_size"] = pixel_size.to_dict()
    if focal_plane is not None:
        doc["focal_plane"] = focal_plane.to_dict()
    if z_scale is not None:
        doc["z_scale"] = z_scale.to_dict()
    return write_json(p, doc)


def set_rig_pixel_size(rig_path: str | os.PathLike, pixel_size_mm: float) -> Path:
    """Set ``[camera] pixel_size_mm`` in a rig file, keeping everything else as written.

    The line is replaced when present, else added right under ``[camera]``.
    """
    import re
    import tomllib

    from .._atomic import write_text

    p = Path(rig_path)
    text = p.read_text(encoding="utf-8")
    try:
        tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"{p}: not valid TOML: {exc}") from None
    lines = text.splitlines(keepends=True)
    value = f"pixel_size_mm = {pixel_size_mm:.6g}  # smdinspect calibrate pixel-size\n"
    section = None
    head = None
    for i, ln in enumerate(lines):
        m = re.match(r"^\s*\[([^\]]+)\]\s*(#.*)?$", ln)
        if m:
            section = m.group(1).strip()
            if section == "camera":
                head = i
            continue
        if section == "camera" and re.match(r"^\s*pixel_size_mm\s*=", ln):
            lines[i] = value
            break
    else:
        if head is None:
            raise InputError(f"{p}: no [camera] table to hold pixel_size_mm")
        lines.insert(head + 1, value)
    out = "".join(lines)
    tomllib.loads(out)
    return write_text(p, out)


def apply_calibration_file(surface, path: str | os.PathLike | None):
    """``surface`` corrected by the calibration file at ``path`` (unchanged for ``None``).

    The focal-plane correction is subtracted from the heights (in the sweep's nominal z,
    which it was measured in), then z is scaled; the file's pixel size is used when the
    surface has none (a pixel size the stack states is kept).
    """
    from dataclasses import replace

    if path is None:
        return surface
    cal = read_calibration(path)
    if cal["focal_plane"] is not None:
        surface = apply_calibration(surface, cal["focal_plane"])
    if cal["z_scale"] is not None:
        surface = apply_z_scale(surface, cal["z_scale"])
    if surface.pixel_size_mm is None and cal["pixel_size_mm"] is not None:
        surface = replace(surface, pixel_size_mm=float(cal["pixel_size_mm"]))
    return surface
