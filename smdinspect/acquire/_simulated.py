"""Build the simulated camera's scene, optics and sensor from a rig file's tables.

``[camera] kind = "simulated"`` takes either a synthetic test scene or a reference board::

    [camera]
    kind = "simulated"
    scene = "cone"                # cone | staircase | slanted_plane | half_textured
    seed = 7                      # sensor noise (and texture, unless scene_options.seed)
    sensor = "low"                # a SensorConfig preset, or a [camera.sensor] table
    [camera.scene_options]        # keyword arguments of smdinspect.synth.cone_scene
    size_px = 128
    height_mm = 0.6

    # or
    board = "../references/demo_board.json"   # relative to the rig file
    defects = "R3.1:insufficient,U1.4:bridge"
    [camera.scene_options]        # keyword arguments of smdinspect.synth.board_scene
    pixel_size_mm = 0.015

The optics come from ``[optics]``: without ``magnification`` it is chosen so the object
pixel equals the scene's (:meth:`smdinspect.optics.Optics.for_pixel_size`); with it, the
two must agree.
"""

from __future__ import annotations

from typing import Any, Callable

from ..errors import InputError

__all__ = ["SCENES", "build_optics", "build_scene", "build_sensor"]

#: Scene names a rig file may give, and the smdinspect.synth function that builds each.
SCENES = {
    "cone": "cone_scene",
    "staircase": "staircase_scene",
    "slanted_plane": "slanted_plane_scene",
    "half_textured": "half_textured_scene",
}


def build_scene(options: dict[str, Any], *, resolve: Callable[[str], Any]) -> Any:
    """The :class:`smdinspect.synth.Scene` a simulated ``[camera]`` table names."""
    from .. import synth

    extra = options.get("scene_options", {}) or {}
    if not isinstance(extra, dict):
        raise InputError("[camera.scene_options] must be a table")
    seed = options.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise InputError(f"[camera] seed must be an integer >= 0; got {seed!r}")
    kwargs = {"seed": seed, **extra}
    if "board" in options:
        return _board_scene(options, kwargs, resolve)
    name = options.get("scene")
    if name not in SCENES:
        raise InputError(f"[camera] scene must be one of {', '.join(SCENES)}; got {name!r}")
    if "defects" in options:
        raise InputError("[camera] defects only apply to a board = \"...\" scene")
    func = getattr(synth, SCENES[name])
    try:
        return func(**kwargs)
    except TypeError as exc:
        raise InputError(f"[camera.scene_options] for scene {name!r}: {exc}") from None


def _board_scene(options: dict[str, Any], kwargs: dict[str, Any], resolve) -> Any:
    try:
        from ..inspect import load_board
        from ..synth import board_scene, parse_defects
    except ImportError as exc:
        raise InputError(f"board scenes are not available in this build ({exc})") from None
    path = resolve(options["board"])
    board = load_board(path)
    defects = options.get("defects", "")
    if not isinstance(defects, str):
        raise InputError(f"[camera] defects must be a string like \"R3.1:insufficient\"; "
                         f"got {defects!r}")
    parsed = parse_defects(defects, board=board) if defects else {}
    if "shape" in kwargs and isinstance(kwargs["shape"], list):
        kwargs["shape"] = tuple(kwargs["shape"])
    for key in ("offset_mm",):
        if isinstance(kwargs.get(key), list):
            kwargs[key] = tuple(kwargs[key])
    try:
        scene, _labels = board_scene(board, defects=parsed, **kwargs)
    except TypeError as exc:
        raise InputError(f"[camera.scene_options] for a board scene: {exc}") from None
    return scene


def build_optics(optics: dict[str, Any], scene: Any) -> Any:
    """The :class:`smdinspect.optics.Optics` for ``scene`` from the ``[optics]`` table."""
    from ..optics import Optics

    p = float(scene.pixel_size_mm)
    if "magnification" not in optics:
        return Optics.for_pixel_size(p, **optics)
    o = Optics(**optics)
    if abs(o.pixel_size_mm - p) > 1e-3 * p:
        raise InputError(
            f"[optics] gives an object pixel of {o.pixel_size_mm:g} mm (pixel_pitch_mm / "
            f"magnification) but the simulated scene has {p:g} mm; drop magnification to "
            "derive it from the scene"
        )
    return o


def build_sensor(spec: Any) -> Any:
    """A :class:`smdinspect.synth.SensorConfig` from a preset name or a table."""
    from ..synth import SensorConfig

    if spec is None:
        return SensorConfig()
    if isinstance(spec, str):
        return SensorConfig.preset(spec)
    if not isinstance(spec, dict):
        raise InputError(f"[camera] sensor must be a preset name or a table; got {spec!r}")
    spec = dict(spec)
    preset = spec.pop("preset", None)
    try:
        return SensorConfig.preset(preset, **spec) if preset else SensorConfig(**spec)
    except TypeError as exc:
        raise InputError(f"[camera.sensor]: {exc}") from None
