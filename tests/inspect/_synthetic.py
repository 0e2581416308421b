"""Helpers of the inspection tests: measured surfaces made from synthetic board truth."""

from __future__ import annotations

import numpy as np

from smdinspect.inspect import load_board
from smdinspect.sff import Surface
from smdinspect.synth._board_scene import board_scene, parse_defects

DEMO = "references/demo_board.json"
DENSE = "references/dense_board.json"
STEP_MM = 0.05
Z_MM = np.arange(-0.1, 1.8, STEP_MM)

#: One joint (or component) of every defect class on the demo board, with ok joints left.
ALL_DEFECTS = ("U1.2:bridge,U1.6:lifted_lead,U1.4:insufficient,U1.8:excess,C1.1:missing,"
               "R2.2:excess,R2.1:insufficient,R3.1:tombstone,C2.1:component_missing,"
               "R1.1:component_shifted")


def truth_surface(board, defects: str, *, seed: int, pixel_size_mm: float = 0.02,
                  offset_mm=None, rotate_deg=None, noise_mm: float = 0.003,
                  hole_fraction: float = 0.05, dead_box=None, params=None,
                  finish: str = "enig", fiducials: bool = True, shape=None):
    """A Surface from a board scene's true heights, with noise and unreliable holes.

    ``dead_box``: (joint_id, half_x_mm, half_y_mm) marks a box around a joint's pad
    unreliable (a textureless region). ``params``, ``finish``, ``shape``: see
    :func:`board_scene`; ``fiducials=False`` removes the board's fiducials (from the
    scene and from the board returned, which is the one to inspect against).
    Returns (surface, labels, board).
    """
    import dataclasses

    b = load_board(board) if isinstance(board, str) else board
    if not fiducials:
        b = dataclasses.replace(b, fiducials=())
    scene, labels = board_scene(b, defects=parse_defects(defects, board=b),
                                pixel_size_mm=pixel_size_mm, seed=seed, offset_mm=offset_mm,
                                rotate_deg=rotate_deg, params=params, finish=finish,
                                shape=shape)
    rng = np.random.default_rng(seed)
    h = scene.height_mm + rng.normal(0.0, noise_mm, scene.height_mm.shape).astype(np.float32)
    reliable = rng.random(h.shape) >= hole_fraction
    if dead_box is not None:
        from smdinspect.inspect._geometry import apply2d, polygon_mask, world_to_pixel

        jid, hx, hy = dead_box
        c = np.array(b.joint(jid).center_mm)
        box = c + np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]])
        T = np.array(labels["placement"]["board_to_world"])
        reliable &= ~polygon_mask(world_to_pixel(apply2d(T, box), shape=h.shape,
                                                 pixel_size_mm=pixel_size_mm), h.shape)
    aif = np.round(np.clip(scene.albedo, 0, 1) * 255).astype(np.uint8)
    surface = Surface(height_mm=h, confidence=reliable.astype(np.float32), reliable=reliable,
                      f_peak=np.ones_like(h), sigma_mm=np.full(h.shape, 0.1, np.float32),
                      reliability_db=np.full(h.shape, 30.0, np.float32), aif=aif,
                      pixel_size_mm=pixel_size_mm, z_mm=Z_MM.copy())
    return surface, labels, b


def expected(labels) -> dict[str, set[str]]:
    """Acceptable verdicts per joint: its class; a bridge's partner may be called bridge."""
    out = {}
    for j in labels["joints"]:
        ok = set(j.get("accept", [j["class"]]))
        if "bridged_by" in j:
            ok.add("bridge")
        out[j["id"]] = ok
    return out


def height_errors(result, labels, classes=("ok", "insufficient", "excess")) -> np.ndarray:
    """Measured − true max solder height (mm) of the joints of ``classes``."""
    lab = {j["id"]: j for j in labels["joints"]}
    return np.array([j.measured_max_mm - lab[j.id]["true_height_mm"] for j in result.joints
                     if lab[j.id]["class"] in classes and "bridged_by" not in lab[j.id]
                     and j.verdict.value != "unreliable"])


def render_board_stack(root, defects: str, *, seed: int, textureless_joint: str | None = None,
                       pixel_size_mm: float = 0.02, params=None, finish: str = "enig",
                       board=None, z_mm=None):
    """Render the demo board with ``defects`` into a focal stack at ``root``.

    ``textureless_joint``: the albedo around that joint's pad (pad + 0.25 mm) is made
    uniform and matt, so shape from focus cannot measure it. ``params``, ``finish``:
    see :func:`board_scene`; ``board``: another Board (e.g. the demo board without
    fiducials); ``z_mm``: the sweep (default :data:`Z_MM`). Returns (stack, labels).
    """
    from smdinspect.inspect._geometry import apply2d, polygon_mask, world_to_pixel
    from smdinspect.optics import Optics
    from smdinspect.synth import Scene, render_stack

    b = load_board(DEMO) if board is None else board
    scene, labels = board_scene(b, defects=parse_defects(defects, board=b),
                                pixel_size_mm=pixel_size_mm, seed=seed, params=params,
                                finish=finish)
    if textureless_joint is not None:
        poly = b.joint(textureless_joint).polygon_mm
        lo, hi = poly.min(axis=0) - 0.25, poly.max(axis=0) + 0.25
        box = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]])
        T = np.array(labels["placement"]["board_to_world"])
        shape = scene.height_mm.shape
        m = polygon_mask(world_to_pixel(apply2d(T, box), shape=shape,
                                        pixel_size_mm=pixel_size_mm), shape)
        albedo = np.array(scene.albedo)
        albedo[m] = albedo[m].reshape(-1, 3).mean(axis=0)
        specular = np.array(scene.specular)
        specular[m] = 0.0
        scene = Scene(scene.height_mm, albedo, pixel_size_mm, specular, scene.name, dict(scene.meta))
    stack = render_stack(scene, Z_MM if z_mm is None else z_mm, optics=Optics(pixel_pitch_mm=pixel_size_mm), seed=seed,
                         out=root, previews=False)
    return stack, labels


def part_crop(board, ref: str, *, pixel_size_mm: float = 0.02, margin_mm: float = 0.8,
              rotate_deg: float = 0.0):
    """A field of view around one part: the board with only that part (no fiducials),
    and the ``offset_mm`` and ``shape`` of :func:`board_scene` that centre it in an image
    holding its body and pads with ``margin_mm`` to spare, turned by ``rotate_deg``.

    Returns (board, offset_mm, shape).
    """
    import dataclasses
    import math

    b = load_board(board) if isinstance(board, str) else board
    part = b.component(ref)
    pts = np.vstack([part.body_polygon_mm()]
                    + [np.asarray(j.polygon_mm) for j in part.joints])
    centre = (pts.min(0) + pts.max(0)) / 2
    a = math.radians(rotate_deg)
    R = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    turned = (pts - centre) @ R.T
    ext = turned.max(0) - turned.min(0) + 2 * margin_mm
    shape = tuple(int(math.ceil(e / pixel_size_mm)) + 1 for e in ext[::-1])
    off = -R @ (centre - np.asarray(b.size_mm) / 2)
    one = dataclasses.replace(b, components=(part,), fiducials=())
    return one, (float(off[0]), float(off[1])), shape


def inspect_placed(surface, board, labels, config=None):
    """Inspect ``surface`` at the scene's true placement (``labels``), without
    registration: the verdict rules alone, on a crop where the board's layout that
    registration needs is out of view."""
    from smdinspect.inspect import InspectConfig
    from smdinspect.inspect._inspect import _inspect_located
    from smdinspect.inspect._register import RegistrationResult

    T = np.array(labels["placement"]["board_to_world"], np.float64)
    reg = RegistrationResult(transform=T, fitness=float("nan"), rmse_mm=float("nan"),
                             converged=True, method="truth")
    return _inspect_located(surface, board, reg, config or InspectConfig())


def placed_mask(surface, labels, polygon_mm) -> np.ndarray:
    """Pixels of ``surface`` inside a board-coordinate polygon, at the scene's placement."""
    from smdinspect.inspect._geometry import apply2d, polygon_mask, world_to_pixel

    T = np.array(labels["placement"]["board_to_world"])
    shape = surface.height_mm.shape
    return polygon_mask(world_to_pixel(apply2d(T, polygon_mm), shape=shape,
                                       pixel_size_mm=surface.pixel_size_mm), shape)
