"""Test helpers: KiCad board files of each release written from a known board.

The writer works in KiCad's own terms (y down, angles counter-clockwise on screen, pad
angles absolute, pad positions in the unrotated footprint frame) with its own arithmetic,
so the importer is checked against an independent derivation of the same geometry.
"""

from __future__ import annotations

import math
import uuid

import numpy as np

from smdinspect.inspect import load_board

VERSIONS = {6: 20211014, 7: 20221018, 8: 20240108, 9: 20241229}

# Footprint library names for the board model's packages.
FOOTPRINT = {
    ("0402", "resistor"): "Resistor_SMD:R_0402_1005Metric",
    ("0402", "capacitor"): "Capacitor_SMD:C_0402_1005Metric",
    ("0603", "resistor"): "Resistor_SMD:R_0603_1608Metric",
    ("0603", "capacitor"): "Capacitor_SMD:C_0603_1608Metric",
    ("0805", "resistor"): "Resistor_SMD:R_0805_2012Metric",
    ("0805", "capacitor"): "Capacitor_SMD:C_0805_2012Metric",
    ("1206", "resistor"): "Resistor_SMD:R_1206_3216Metric",
    ("1206", "capacitor"): "Capacitor_SMD:C_1206_3216Metric",
    ("SOIC-8", "ic"): "Package_SO:SOIC-8_3.9x4.9mm_P1.27mm",
    ("SOIC-16", "ic"): "Package_SO:SOIC-16_3.9x9.9mm_P1.27mm",
    ("TSSOP-8", "ic"): "Package_SO:TSSOP-8_4.4x3mm_P0.65mm",
    ("LQFP-32", "ic"): "Package_QFP:LQFP-32_7x7mm_P0.8mm",
}

ORIGIN = (100.0, 40.0)     # KiCad coordinates of the board's top-left corner


def _uid(rng) -> str:
    return str(uuid.UUID(int=int(rng.integers(0, 2 ** 63)) << 64 | int(rng.integers(0, 2 ** 63))))


def _f(v: float) -> str:
    s = f"{v:.6f}".rstrip("0").rstrip(".")
    return "0" if s in ("-0", "") else s


def header(version: int) -> list[str]:
    out = [f"(kicad_pcb (version {VERSIONS[version]})"]
    if version >= 8:
        out.append(f'  (generator "pcbnew") (generator_version "{version}.0")')
    else:
        out.append("  (generator pcbnew)")
    out.append("  (general (thickness 1.6))")
    out.append('  (paper "A4")')
    out.append('  (layers (0 "F.Cu" signal) (31 "B.Cu" signal) (44 "Edge.Cuts" user))')
    out.append('  (net 0 "")')
    out.append('  (net 1 "GND")')
    return out


def stroke(version: int) -> str:
    return "(width 0.1)" if version == 6 else "(stroke (width 0.1) (type default))"


def tag(version: int, rng) -> str:
    return f"(tstamp {_uid(rng)})" if version < 8 else f'(uuid "{_uid(rng)}")'


def outline(version: int, width: float, height: float, rng, *, style: str = "lines") -> list[str]:
    x0, y0 = ORIGIN
    if style == "rect":
        fill = " (fill none)" if version >= 8 else ""
        return [f'  (gr_rect (start {_f(x0)} {_f(y0)}) (end {_f(x0 + width)} {_f(y0 + height)}) '
                f'{stroke(version)}{fill} (layer "Edge.Cuts") {tag(version, rng)})']
    pts = [(x0, y0), (x0 + width, y0), (x0 + width, y0 + height), (x0, y0 + height)]
    return [f'  (gr_line (start {_f(a[0])} {_f(a[1])}) (end {_f(b[0])} {_f(b[1])}) '
            f'{stroke(version)} (layer "Edge.Cuts") {tag(version, rng)})'
            for a, b in zip(pts, pts[1:] + pts[:1])]


def text_fields(version: int, ref: str, value: str, angle: float, rng, layer="F") -> list[str]:
    if version >= 8:
        return [f'    (property "Reference" "{ref}" (at 0 -1.5 {_f(angle)}) (layer "{layer}.SilkS") '
                f'{tag(version, rng)} (effects (font (size 1 1) (thickness 0.15))))',
                f'    (property "Value" "{value}" (at 0 1.5 {_f(angle)}) (layer "{layer}.Fab") '
                f'{tag(version, rng)} (effects (font (size 1 1) (thickness 0.15))))']
    return [f'    (fp_text reference "{ref}" (at 0 -1.5 {_f(angle)}) (layer "{layer}.SilkS") '
            f'(effects (font (size 1 1) (thickness 0.15))) {tag(version, rng)})',
            f'    (fp_text value "{value}" (at 0 1.5 {_f(angle)}) (layer "{layer}.Fab") '
            f'(effects (font (size 1 1) (thickness 0.15))) {tag(version, rng)})']


def footprint(version: int, name: str, ref: str, x: float, y: float, angle: float,
              pads: list[str], rng, *, layer: str = "F.Cu", attr: str = "smd",
              value: str = "x") -> list[str]:
    side = layer[0]
    at = f"(at {_f(x)} {_f(y)}{' ' + _f(angle) if angle else ''})"
    out = [f'  (footprint "{name}" (layer "{layer}")']
    if version < 8:
        out.append("    (tedit 5F68FEEE)")
    out.append(f"    {tag(version, rng)}")
    out.append(f"    {at}")
    out.append('    (descr "generated for a test")')
    out += text_fields(version, ref, value, angle, rng, side)
    if attr:
        out.append(f"    (attr {attr})")
    out.append(f'    (fp_line (start -0.5 -0.3) (end 0.5 -0.3) {stroke(version)} '
               f'(layer "{side}.SilkS") {tag(version, rng)})')
    out += pads
    if version >= 9:
        out.append("    (embedded_fonts no)")
    out.append("  )")
    return out


def pad(version: int, number: str, shape: str, x: float, y: float, angle: float,
        size: tuple[float, float], rng, *, layers: str = '"F.Cu" "F.Paste" "F.Mask"',
        kind: str = "smd", extra: str = "") -> str:
    at = f"(at {_f(x)} {_f(y)}{' ' + _f(angle) if angle else ''})"
    rr = " (roundrect_rratio 0.25)" if shape == "roundrect" else ""
    return (f'    (pad "{number}" {kind} {shape} {at} (size {_f(size[0])} {_f(size[1])}) '
            f'(layers {layers}){rr}{extra} (net 1 "GND") {tag(version, rng)})')


def board_to_kicad(board_path, version: int, *, shape: str = "rect", seed: int = 0,
                   pad_local_angle: float = 0.0, extra_footprints=(),
                   outline_style: str = "lines") -> str:
    """A ``.kicad_pcb`` text describing the board file at ``board_path``.

    Chips are drawn as KiCad draws them (pads along x, pad 1 left); gull-wing parts with
    the pin rows vertical and pin 1 at the top left, i.e. the footprint turned by 90°
    from the board model's frame. ``pad_local_angle`` (0 or 90) writes every pad rotated
    in the footprint by that angle with its size swapped (as some libraries do).
    """
    rng = np.random.default_rng(seed)
    board = load_board(board_path)
    w, h = board.size_mm
    lines = header(version) + outline(version, w, h, rng, style=outline_style)
    x0, y0 = ORIGIN
    for f in board.fiducials:
        fx, fy = x0 + f.x_mm, y0 + (h - f.y_mm)
        p = pad(version, "1", "circle", 0, 0, 0, (f.diameter_mm, f.diameter_mm), rng,
                layers='"F.Cu" "F.Mask"')
        lines += footprint(version, "Fiducial:Fiducial_0.6mm_Mask1.2mm", f.id, fx, fy, 0,
                           [p], rng)
    for c in board.components:
        # Footprint angle (screen CCW): chips as the model, gull-wing +90°.
        turn = 90.0 if c.kind == "gullwing" else 0.0
        angle = (c.rotation_deg + turn) % 360.0
        pads = []
        for j in c.joints:
            local = c.to_local(j.polygon_mm)                 # model frame, y up
            # model frame → footprint frame (y up): rotate by -turn; then y down.
            a = math.radians(-turn)
            rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
            fp = local @ rot.T
            fp[:, 1] = -fp[:, 1]
            cx, cy = (fp.max(axis=0) + fp.min(axis=0)) / 2
            sx, sy = np.ptp(fp[:, 0]), np.ptp(fp[:, 1])
            if pad_local_angle:
                sx, sy = sy, sx
            pads.append(pad(version, j.pad_number, shape, cx, cy,
                            (angle + pad_local_angle) % 360.0, (sx, sy), rng))
        kx, ky = x0 + c.x_mm, y0 + (h - c.y_mm)
        lines += footprint(version, FOOTPRINT[(c.package, c.style)], c.ref, kx, ky, angle,
                           pads, rng)
    for fp_lines in extra_footprints:
        lines += fp_lines
    lines.append(")")
    return "\n".join(lines) + "\n"
