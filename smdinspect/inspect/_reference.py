"""The reference surface of a board: what a perfect board should look like from above.

Built from the :class:`~smdinspect.inspect.Board` as a set of prisms (board slab,
component bodies, gull-wing leads, nominal solder fillets), each a convex polygon in the
BOARD frame with a planar top. The prisms become

* a height raster in any world grid under a placement ``T`` (:func:`render_reference`),
  used by the coarse registration, and
* a trimesh mesh (:func:`reference_mesh`) sampled as points with normals
  (:func:`reference_points`), the target of the fine ICP registration.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from ._geometry import apply2d, polygon_mask, world_to_pixel

__all__ = ["Prism", "body_top_mm", "lead_top_mm", "reference_mesh", "reference_points", "reference_prisms", "render_reference"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Prism:
    """A vertical prism: convex ``polygon_mm`` (BOARD frame) from ``bottom_mm`` up to the
    plane ``z = top[0]·x + top[1]·y + top[2]`` (BOARD frame, mm)."""

    kind: str            # "board", "body", "lead", "fillet"
    ref: str             # component ref ("" for the board)
    polygon_mm: np.ndarray
    top: tuple[float, float, float]
    bottom_mm: float

    def top_at(self, xy: np.ndarray) -> np.ndarray:
        xy = np.asarray(xy, np.float64).reshape(-1, 2)
        return self.top[0] * xy[:, 0] + self.top[1] * xy[:, 1] + self.top[2]

    @property
    def max_top_mm(self) -> float:
        return float(self.top_at(self.polygon_mm).max())


def body_top_mm(comp) -> float:
    """Height of a component's body top above the board (mm).

    Chips: ``standoff_mm + body_height_mm`` (the body sits on the solder layer G).
    Gull-wing packages: ``body_height_mm`` is the package's total height above the
    board (JEDEC "A"; the mould starts ``standoff_mm`` above the board), as the shipped
    board files and the board simulator use it.
    """
    if comp.kind == "gullwing":
        return float(comp.body_height_mm)
    return float(comp.standoff_mm + comp.body_height_mm)


def lead_top_mm(comp) -> float:
    """Nominal top of a gull-wing lead's foot above the board: solder layer under the
    foot + lead thickness (mm); 0 for parts without leads."""
    lead = comp.lead or {}
    return float(lead.get("solder_thickness_mm", 0.0)) + float(lead.get("thickness_mm", 0.0))


def _ramp(polygon: np.ndarray, p0: np.ndarray, direction: np.ndarray, z0: float,
          z1: float, length: float) -> tuple[float, float, float]:
    """Plane coefficients of a ramp: ``z0`` at ``p0`` falling to ``z1`` after ``length``
    along the unit vector ``direction``."""
    slope = (z1 - z0) / max(length, 1e-9)
    a, b = slope * direction[0], slope * direction[1]
    return float(a), float(b), float(z0 - a * p0[0] - b * p0[1])


def reference_prisms(board, *, fillets: bool = True, slab: bool = False) -> list[Prism]:
    """Prisms of the reference board (BOARD frame).

    Parameters
    ----------
    board : Board
    fillets : bool
        Include the nominal solder fillets (chip ends: a ramp from the nominal height at
        the body end down to the pad's outer edge; gull-wing: a toe ramp from the lead
        top down to the pad's outer edge).
    slab : bool
        Include the board slab (z from ``-thickness_mm`` to 0).
    """
    prisms: list[Prism] = []
    if slab:
        prisms.append(Prism("board", "", board.outline_mm(),
                            (0.0, 0.0, 0.0), -float(board.thickness_mm)))
    for comp in board.components:
        top = body_top_mm(comp)
        prisms.append(Prism("body", comp.ref, comp.body_polygon_mm(), (0.0, 0.0, top),
                            float(comp.standoff_mm)))
        for joint in comp.joints:
            out = np.asarray(joint.outward, np.float64)
            pad = np.asarray(joint.polygon_mm, np.float64)
            pad_u = pad @ out
            if comp.kind == "gullwing" and comp.lead:
                lead = comp.lead
                g = float(lead.get("solder_thickness_mm", 0.03))
                t = float(lead["thickness_mm"])
                lead_poly = comp.termination_polygon_mm(joint.id)
                lu = lead_poly @ out
                u_mould, u_toe = float(lu.min()), float(lu.max())
                u_foot = u_toe - float(lead["foot_length_mm"])
                foot = _clip_band(lead_poly, out, u_foot, u_toe)
                bend = _clip_band(lead_poly, out, u_mould, u_foot)
                prisms.append(Prism("lead", comp.ref, foot, (0.0, 0.0, g + t), g))
                if bend is not None:
                    p0 = out * u_mould
                    prisms.append(Prism("lead", comp.ref, bend,
                                        _ramp(bend, p0, out, float(lead["exit_height_mm"]),
                                              g + t, u_foot - u_mould), g))
                if fillets:
                    toe = _clip_band(pad, out, u_toe, float(pad_u.max()))
                    if toe is not None:
                        p0 = out * u_toe
                        prisms.append(Prism("fillet", comp.ref, toe,
                                            _ramp(toe, p0, out, g + t, 0.0,
                                                  float(pad_u.max()) - u_toe), 0.0))
            elif fillets:
                body_u = float((comp.body_polygon_mm() @ out).max())
                outer = float(pad_u.max())
                band = _clip_band(pad, out, body_u, outer)
                if band is not None:
                    p0 = out * body_u
                    prisms.append(Prism("fillet", comp.ref, band,
                                        _ramp(band, p0, out, float(joint.nominal_height_mm),
                                              0.0, outer - body_u), 0.0))
    return prisms


def _clip_band(poly: np.ndarray, direction: np.ndarray, u0: float, u1: float):
    """The part of convex ``poly`` with ``u0 <= p·direction <= u1`` (None when empty)."""
    if u1 - u0 <= 1e-9:
        return None
    pts = np.asarray(poly, np.float64)
    for sign, bound in ((1.0, u0), (-1.0, -u1)):
        out = []
        n = len(pts)
        for i in range(n):
            a, b = pts[i], pts[(i + 1) % n]
            da, db = sign * (a @ direction) - bound, sign * (b @ direction) - bound
            if da >= 0:
                out.append(a)
            if (da >= 0) != (db >= 0):
                out.append(a + (b - a) * (da / (da - db)))
        pts = np.array(out)
        if len(pts) < 3:
            return None
    return pts


def render_reference(
    prisms: list[Prism],
    T: np.ndarray,
    *,
    shape: tuple[int, int],
    pixel_size_mm: float,
    origin_mm: tuple[float, float] = (0.0, 0.0),
    board=None,
) -> tuple[np.ndarray, np.ndarray]:
    """Rasterise the reference heights into a world grid.

    Parameters
    ----------
    prisms : list of Prism
    T : (3, 3) float64
        Placement, WORLD = T · BOARD.
    shape : (H, W)
        Grid size; pixel (row, col) sits at world ``x = origin_x + col·p``,
        ``y = origin_y + (H−1−row)·p``.
    pixel_size_mm : float
    origin_mm : (float, float)
        World position of the grid's pixel (H−1, 0).
    board : Board, optional
        When given, the mask is the board's outline; otherwise the union of the prisms.

    Returns
    -------
    height_mm : (H, W) float32
        Top-most reference height (0 on the bare board).
    mask : (H, W) bool
        Where the reference is defined.
    """
    p = float(pixel_size_mm)
    off = np.asarray(origin_mm, np.float64)
    height = np.zeros(shape, np.float32)
    if board is not None:
        outline = apply2d(T, board.outline_mm()) - off
        mask = polygon_mask(world_to_pixel(outline, shape=shape, pixel_size_mm=p), shape)
    else:
        mask = np.zeros(shape, bool)
    rows, cols = np.indices(shape)
    for prism in prisms:
        poly_w = apply2d(T, prism.polygon_mm) - off
        poly_px = world_to_pixel(poly_w, shape=shape, pixel_size_mm=p)
        c0, r0 = np.floor(poly_px.min(axis=0)).astype(int) - 1
        c1, r1 = np.ceil(poly_px.max(axis=0)).astype(int) + 2
        c0, r0 = max(c0, 0), max(r0, 0)
        c1, r1 = min(c1, shape[1]), min(r1, shape[0])
        if c1 <= c0 or r1 <= r0:
            continue
        sub = polygon_mask(poly_px - [c0, r0], (r1 - r0, c1 - c0))
        if not sub.any():
            continue
        if board is None:
            mask[r0:r1, c0:c1] |= sub
        rr, cc = rows[r0:r1, c0:c1][sub], cols[r0:r1, c0:c1][sub]
        wx = cc * p + off[0]
        wy = (shape[0] - 1 - rr) * p + off[1]
        bxy = apply2d(np.linalg.inv(T), np.column_stack([wx, wy]))
        z = prism.top_at(bxy).astype(np.float32)
        height[rr, cc] = np.maximum(height[rr, cc], z)
    return height, mask


def reference_mesh(board, *, fillets: bool = True):
    """The reference board as one :class:`trimesh.Trimesh` (BOARD frame, mm).

    The board slab, every body, lead and nominal fillet as closed prisms.
    """
    try:
        import trimesh
    except ImportError as exc:  # pragma: no cover - dependency of the package
        raise ImportError("the reference surface needs trimesh: pip install trimesh") from exc
    meshes = []
    for prism in reference_prisms(board, fillets=fillets, slab=True):
        v, f = _prism_mesh(prism)
        meshes.append(trimesh.Trimesh(vertices=v, faces=f, process=False))
    return trimesh.util.concatenate(meshes)


def _prism_mesh(prism: Prism) -> tuple[np.ndarray, np.ndarray]:
    poly = np.asarray(prism.polygon_mm, np.float64)
    x, y = poly[:, 0], poly[:, 1]
    if 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)) < 0:
        poly = poly[::-1]
    n = len(poly)
    top = prism.top_at(poly)
    verts = np.vstack([np.column_stack([poly, np.full(n, prism.bottom_mm)]),
                       np.column_stack([poly, top])])
    faces = []
    for i in range(1, n - 1):
        faces.append([n, n + i, n + i + 1])      # top, counter-clockwise seen from +z
        faces.append([0, i + 1, i])               # bottom, facing -z
    for i in range(n):
        j = (i + 1) % n
        faces.append([i, j, n + j])
        faces.append([i, n + j, n + i])
    return verts, np.array(faces, np.int64)


def reference_points(
    board,
    *,
    spacing_mm: float = 0.03,
    seed: int = 0,
    fillets: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Sample the visible reference surface as points with normals (BOARD frame).

    Faces looking down and points hidden under a higher surface (e.g. the board top
    under a body) are dropped: the camera looks from +z and cannot see them.

    Parameters
    ----------
    board : Board
    spacing_mm : float
        Mean distance between samples.
    seed : int

    Returns
    -------
    points : (N, 3) float64
        x_mm, y_mm, z_mm in the BOARD frame.
    normals : (N, 3) float64
        Unit outward normals.
    """
    import trimesh

    mesh = reference_mesh(board, fillets=fillets)
    count = int(mesh.area / spacing_mm ** 2)
    pts, face = trimesh.sample.sample_surface(mesh, count, seed=seed)
    normals = np.asarray(mesh.face_normals)[face]
    keep = normals[:, 2] > -0.5
    pts, normals = np.asarray(pts)[keep], normals[keep]
    # Drop points below the top-most surface at their (x, y) (hidden from the camera).
    w, h = board.size_mm
    q = spacing_mm / 2.0
    shape = (int(np.ceil(h / q)) + 3, int(np.ceil(w / q)) + 3)
    prisms = reference_prisms(board, fillets=fillets, slab=True)
    T = np.eye(3)
    top, _ = render_reference(prisms, T, shape=shape, pixel_size_mm=q, origin_mm=(-q, -q))
    from scipy.ndimage import maximum_filter

    top = maximum_filter(top, size=3)  # walls sit on the outline: look one pixel around
    cols = np.clip(np.round((pts[:, 0] + q) / q).astype(int), 0, shape[1] - 1)
    rows = np.clip(np.round(shape[0] - 1 - (pts[:, 1] + q) / q).astype(int), 0, shape[0] - 1)
    visible = pts[:, 2] >= top[rows, cols] - 0.02
    # Side walls are visible where they stand (their z lies below the local max only
    # because the max filter reaches over the top): keep walls (horizontal normals).
    visible |= np.abs(normals[:, 2]) < 0.5
    # ... except walls under a higher body (e.g. a chip's end face hidden under nothing
    # is fine; a board edge beneath a body overhang does not occur).
    # Also drop the board's outer side walls: they are below z = 0.
    visible &= pts[:, 2] >= -1e-6
    return pts[visible], normals[visible]
