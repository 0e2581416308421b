"""Rig files (TOML): what stage, camera, optics and sweep make up an acquisition rig.

A rig file has five tables; unknown keys are errors (a typo never passes silently)::

    [stage]                       # smdinspect.acquire.StageConfig
    protocol = "grbl"
    port = "/dev/ttyUSB0"         # any pyserial URL: COM3, socket://host:23, rfc2217://...
    baud = 115200
    timeout_s = 2.0               # every read
    z_min_mm = -40.0              # soft limits, machine coordinates
    z_max_mm = -1.0
    feed_mm_min = 120.0
    home = true                   # $H after connecting
    # fake = true + [stage.fake] starts an in-process fake GRBL on a pty instead

    [mapping]                     # z_mm = focus_offset_mm + direction * MPos.z
    focus_offset_mm = 21.35
    direction = 1

    [camera]
    kind = "opencv"               # opencv | folder | simulated | genicam
    device = 0
    pixel_size_mm = 0.012         # object side; else derived from [optics]

    [optics]                      # smdinspect.optics.Optics fields (stored in stack.json)
    magnification = 1.0

    [sweep]                       # smdinspect.acquire.SweepConfig
    z_start_mm = -0.2
    z_stop_mm = 1.2
    step_mm = 0.02
    settle_s = 0.1
    backlash_mm = 0.3
    frames_per_step = 2

Relative paths (folder camera, board file) are taken relative to the rig file's folder.

The rig *fingerprint* (:attr:`RigConfig.sha256`) is the SHA-256 of the canonical JSON of
everything that decides what a stack contains: ``[sweep]``, ``[mapping]``, ``[camera]``,
``[optics]``, the stage's protocol, soft limits, feed, tolerance and fake-controller
model, plus the bytes of a referenced board file. Connection details (port, baud,
time-outs, homing/unlock at connect) and injected faults are left out, so a stage that
re-enumerates as another port, or needs ``home = true`` after an alarm, can still resume.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import tomllib
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path
from typing import Any, Callable

from ..errors import CameraError, InputError
from ._camera import Camera, FolderCamera, GenICamCamera, OpenCVCamera, SimulatedCamera
from ._stage import Stage, StageConfig
from ._sweep import SweepConfig, SweepResult, ZMapping, _Session

__all__ = ["CameraConfig", "CameraKind", "Rig", "RigConfig", "acquire", "load_rig", "parse_rig"]

log = logging.getLogger(__name__)


class CameraKind(str, Enum):
    """Camera kinds a rig file may name in ``[camera] kind``."""

    OPENCV = "opencv"
    FOLDER = "folder"
    SIMULATED = "simulated"
    GENICAM = "genicam"


# Keys each camera kind accepts besides "kind" and "pixel_size_mm".
_CAMERA_KEYS = {
    CameraKind.OPENCV: {"device", "width", "height", "exposure", "gain", "grey",
                        "warmup_frames", "flush_frames"},
    CameraKind.FOLDER: {"path", "loop"},
    CameraKind.SIMULATED: {"scene", "board", "defects", "seed", "scene_options",
                           "sensor"},
    CameraKind.GENICAM: {"cti", "serial_number", "exposure_us", "gain_db", "timeout_s"},
}
_STAGE_KEYS = {f for f in StageConfig.__dataclass_fields__} - {"fake_options"}
_SWEEP_KEYS = {f for f in SweepConfig.__dataclass_fields__}
_MAPPING_KEYS = {f for f in ZMapping.__dataclass_fields__}
# stage keys that do not change what a stack contains (left out of the fingerprint)
_CONNECTION_KEYS = {"port", "baud", "timeout_s", "move_timeout_s", "homing_timeout_s",
                    "boot_wait_s", "poll_interval_s", "home", "unlock"}


@dataclass(frozen=True)
class CameraConfig:
    """The rig file's ``[camera]`` table.

    Attributes
    ----------
    kind : CameraKind
    options : dict
        The kind's settings: keyword arguments of :class:`OpenCVCamera`,
        :class:`FolderCamera`, :class:`GenICamCamera`, or the simulated camera's ``scene`` /
        ``board``, ``defects``, ``seed``, ``sensor``, ``scene_options``
        (see :mod:`smdinspect.acquire._simulated`).
    pixel_size_mm : float or None
        Object-side pixel size, if the rig file gives it.
    """

    kind: CameraKind
    options: dict[str, Any] = field(default_factory=dict)
    pixel_size_mm: float | None = None

    def __post_init__(self) -> None:
        try:
            object.__setattr__(self, "kind", CameraKind(self.kind))
        except ValueError:
            choices = ", ".join(k.value for k in CameraKind)
            raise InputError(f"camera kind must be one of {choices}; got {self.kind!r}") from None
        unknown = set(self.options) - _CAMERA_KEYS[self.kind]
        if unknown:
            raise InputError(
                f"unknown key(s) {', '.join(sorted(unknown))} in [camera] for kind "
                f"{self.kind.value!r}; known: {', '.join(sorted(_CAMERA_KEYS[self.kind]))}"
            )
        p = self.pixel_size_mm
        if p is not None and (isinstance(p, bool) or not isinstance(p, (int, float)) or not p > 0):
            raise InputError(f"camera pixel_size_mm must be > 0; got {p!r}")


@dataclass(frozen=True)
class RigConfig:
    """A parsed, validated rig file.

    Attributes
    ----------
    stage : StageConfig
    camera : CameraConfig
    optics : dict
        The ``[optics]`` table (fields of :class:`smdinspect.optics.Optics`).
    sweep : SweepConfig
    mapping : ZMapping
    base_dir : Path
        Folder relative paths are resolved against (the rig file's).
    source : str
        The rig file's path ('' when parsed from a string).
    sha256 : str
        The rig fingerprint (see the module docs).
    """

    stage: StageConfig
    camera: CameraConfig
    optics: dict[str, Any]
    sweep: SweepConfig
    mapping: ZMapping
    base_dir: Path
    source: str = ""
    sha256: str = ""

    def resolve(self, path: str | os.PathLike) -> Path:
        """``path`` relative to the rig file's folder (absolute paths unchanged)."""
        p = Path(os.path.expanduser(str(path)))
        return p if p.is_absolute() else self.base_dir / p

    def machine_plan_mm(self) -> list[float]:
        """Machine z of every planned frame, in sweep order."""
        return [self.mapping.machine_z_mm(z) for z in self.sweep.z_positions_mm()]

    def optics_model(self) -> Any:
        """The ``[optics]`` table as an :class:`smdinspect.optics.Optics`."""
        from ..optics import Optics

        return Optics(**self.optics)


def load_rig(path: str | os.PathLike) -> RigConfig:
    """Read and validate a rig file.

    Raises
    ------
    InputError
        Missing file, bad TOML, unknown or missing keys, bad values, or a sweep that
        leaves the stage's soft limits - each with one line naming the culprit.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"rig file not found: {path}")
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read rig file {path}: {exc}") from None
    return parse_rig(text, base_dir=path.parent, source=str(path))


def parse_rig(text: str, *, base_dir: str | os.PathLike = ".", source: str = "") -> RigConfig:
    """Parse rig-file TOML ``text`` (see :func:`load_rig`)."""
    where = source or "rig file"
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"{where} is not valid TOML: {exc}") from None
    unknown = set(doc) - {"stage", "camera", "optics", "sweep", "mapping"}
    if unknown:
        raise InputError(f"{where}: unknown table(s) {', '.join(sorted(unknown))}; expected "
                         "[stage], [mapping], [camera], [optics], [sweep]")
    for name in ("stage", "camera", "sweep"):
        if name not in doc:
            raise InputError(f"{where} has no [{name}] table")
        if not isinstance(doc[name], dict):
            raise InputError(f"{where}: {name} must be a table")
    base = Path(base_dir)

    stage_doc = dict(doc["stage"])
    fake_doc = stage_doc.pop("fake", False)
    fake_options = None
    if isinstance(fake_doc, dict):  # [stage.fake] table implies fake = true
        fake_options, fake = dict(fake_doc), True
    else:
        fake = fake_doc
    _known(stage_doc, _STAGE_KEYS - {"fake"}, "[stage]", where)
    try:
        stage = StageConfig(**stage_doc, fake=fake, fake_options=fake_options)
    except TypeError as exc:
        raise InputError(f"{where}: [stage]: {exc}") from None
    if stage.fake:
        _check_fake_options(stage.fake_options or {}, where)

    mapping_doc = doc.get("mapping", {})
    _known(mapping_doc, _MAPPING_KEYS, "[mapping]", where)
    mapping = ZMapping(**mapping_doc)

    cam_doc = dict(doc["camera"])
    if "kind" not in cam_doc:
        raise InputError(f"{where}: [camera] needs kind = "
                         f"{' | '.join(repr(k.value) for k in CameraKind)}")
    camera = CameraConfig(kind=cam_doc.pop("kind"), pixel_size_mm=cam_doc.pop("pixel_size_mm", None),
                          options=cam_doc)
    if camera.kind is CameraKind.SIMULATED:
        if ("scene" in camera.options) == ("board" in camera.options):
            raise InputError(f"{where}: a simulated [camera] needs exactly one of scene = "
                             "\"cone\" (a synthetic scene) or board = \"path/to/board.json\"")

    optics = doc.get("optics", {})
    if not isinstance(optics, dict):
        raise InputError(f"{where}: optics must be a table")
    if optics:
        from ..optics import Optics

        _known(optics, set(Optics.__dataclass_fields__), "[optics]", where)
        Optics(**optics)  # validates values

    sweep_doc = doc["sweep"]
    missing = {"z_start_mm", "z_stop_mm", "step_mm"} - set(sweep_doc)
    if missing:
        raise InputError(f"{where}: [sweep] needs {', '.join(sorted(missing))}")
    _known(sweep_doc, _SWEEP_KEYS, "[sweep]", where)
    sweep = SweepConfig(**sweep_doc)

    rig = RigConfig(stage=stage, camera=camera, optics=dict(optics), sweep=sweep,
                    mapping=mapping, base_dir=base, source=source)
    _check_travel(rig, where)
    object.__setattr__(rig, "sha256", _fingerprint(doc, rig))
    return rig


def _known(table: Any, keys: set[str], name: str, where: str) -> None:
    if not isinstance(table, dict):
        raise InputError(f"{where}: {name} must be a table")
    unknown = set(table) - keys
    if unknown:
        raise InputError(f"{where}: unknown key(s) {', '.join(sorted(unknown))} in {name}; "
                         f"known: {', '.join(sorted(keys))}")


def _check_fake_options(options: dict[str, Any], where: str) -> None:
    import inspect

    from ._fake_grbl import FakeGrbl

    known = set(inspect.signature(FakeGrbl.__init__).parameters) - {"self"}
    _known(options, known, "[stage.fake]", where)


def _check_travel(rig: RigConfig, where: str) -> None:
    """Every commanded machine z (frames and the backlash overshoot) within soft limits."""
    plan = rig.machine_plan_mm()
    direction = 1 if plan[-1] > plan[0] else -1
    lo, hi = rig.stage.z_min_mm, rig.stage.z_max_mm
    for z_mm, m in zip(rig.sweep.z_positions_mm(), plan):
        if not lo <= m <= hi:
            raise InputError(f"{where}: sweep z_mm {z_mm:.4f} needs machine Z {m:.4f} mm, outside "
                             f"the stage soft limits {lo} .. {hi} mm")
    pre = plan[0] - direction * rig.sweep.backlash_mm
    if not lo <= pre <= hi:
        raise InputError(f"{where}: the backlash overshoot before the first frame needs machine "
                         f"Z {pre:.4f} mm, outside the stage soft limits {lo} .. {hi} mm")


def _fingerprint(doc: dict[str, Any], rig: RigConfig) -> str:
    stage = {k: v for k, v in doc["stage"].items() if k not in _CONNECTION_KEYS}
    if isinstance(stage.get("fake"), dict):
        stage["fake"] = {k: v for k, v in stage["fake"].items() if k != "faults"}
    content = {
        "stage": stage,
        "mapping": doc.get("mapping", {}),
        "camera": doc["camera"],
        "optics": doc.get("optics", {}),
        "sweep": doc["sweep"],
    }
    board = rig.camera.options.get("board")
    if rig.camera.kind is CameraKind.SIMULATED and board:
        p = rig.resolve(board)
        if p.is_file():
            content["board_file_sha256"] = hashlib.sha256(p.read_bytes()).hexdigest()
    text = json.dumps(content, sort_keys=True, default=str, separators=(",", ":"))
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


# ---------------------------------------------------------------------------------------
class Rig:
    """An opened rig: the stage (and its fake controller, if any) and the camera.

    Use as a context manager. On exit the camera is released and the port closed; a
    block that ends with an exception (Ctrl-C included) sends a feed hold first.

    Attributes
    ----------
    stage : Stage
    camera : Camera
    fake : FakeGrbl or None
    pixel_size_mm : float or None
    optics : dict
        What goes into ``stack.json``'s optics block.
    """

    def __init__(self, config: RigConfig) -> None:
        self.config = config
        self.stage: Stage | None = None
        self.camera: Camera | None = None
        self.fake = None
        self.pixel_size_mm: float | None = config.camera.pixel_size_mm
        self.optics: dict[str, Any] = dict(config.optics)

    def open(self) -> "Rig":
        from ._grbl import GrblStage

        c = self.config
        try:
            port = None
            if c.stage.fake:
                from ._fake_grbl import FakeGrbl

                self.fake = FakeGrbl(**(c.stage.fake_options or {})).start()
                port = self.fake.port
            self.stage = GrblStage(c.stage, port=port)
            # the camera is built first (cheap, validates), the port opened second
            self.camera = self._make_camera()
            self.stage.open()
            self.camera.open()
        except BaseException:
            self.close()
            raise
        if c.camera.kind is not CameraKind.SIMULATED and c.optics:
            model = c.optics_model()
            self.optics = model.to_dict()
            if self.pixel_size_mm is None:
                self.pixel_size_mm = float(model.pixel_size_mm)
        return self

    def close(self) -> None:
        if self.camera is not None:
            try:
                self.camera.close()
            except Exception as exc:  # noqa: BLE001 - closing must not raise
                log.warning("closing the camera failed: %s", exc)
        if self.stage is not None:
            self.stage.close()
        if self.fake is not None:
            self.fake.stop()
            self.fake = None

    def __enter__(self) -> "Rig":
        return self.open()

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None and self.stage is not None:
            self.stage.stop()
        self.close()

    def focus_z_mm(self) -> float:
        """Focused-plane height now, from the machine z the stage reports."""
        if self.stage is None:
            raise CameraError("the simulated camera needs the rig's stage, which is not open")
        return round(self.config.mapping.z_mm(self.stage.position()), 9)

    def _make_camera(self) -> Camera:
        c = self.config
        o = dict(c.camera.options)
        kind = c.camera.kind
        if kind is CameraKind.OPENCV:
            return OpenCVCamera(o.pop("device", 0), **o)
        if kind is CameraKind.FOLDER:
            if "path" not in o:
                raise InputError("a folder [camera] needs path = \"folder/of/images\"")
            return FolderCamera(c.resolve(o.pop("path")), **o)
        if kind is CameraKind.GENICAM:
            if "cti" not in o:
                raise InputError("a genicam [camera] needs cti = \"/path/to/producer.cti\"")
            return GenICamCamera(c.resolve(o.pop("cti")), **o)
        return self._make_simulated(o)

    def _make_simulated(self, o: dict[str, Any]) -> Camera:
        from ._simulated import build_optics, build_scene, build_sensor

        c = self.config
        scene = build_scene(o, resolve=c.resolve)
        optics = build_optics(c.optics, scene)
        sensor = build_sensor(o.get("sensor"))
        self.pixel_size_mm = float(scene.pixel_size_mm)
        self.optics = optics.to_dict()
        return SimulatedCamera(scene, optics=optics, sensor=sensor, seed=int(o.get("seed", 0)),
                               z_source=self.focus_z_mm)


def acquire(
    rig: RigConfig | str | os.PathLike,
    out: str | os.PathLike,
    *,
    resume: bool = False,
    progress: Callable[[int, int], None] | None = None,
) -> SweepResult:
    """Run the sweep a rig file describes and write the stack to ``out``.

    The output folder is checked (and a resume validated against the rig fingerprint)
    before the stage or camera is touched. On any failure, Ctrl-C included, the stage
    gets a feed hold, the port is closed and the frames written so far stay listed in
    ``out/stack.json`` for ``resume=True``.

    Parameters
    ----------
    rig : RigConfig or path
    out : path
        Stack directory.
    resume : bool
    progress : callable(done, total), optional

    Returns
    -------
    SweepResult
    """
    if not isinstance(rig, RigConfig):
        rig = load_rig(rig)
    session = _Session.prepare(
        out, sweep=rig.sweep, mapping=rig.mapping, resume=resume, pixel_size_mm=None,
        optics=None, rig={"stage": rig.stage.protocol.value, "camera": rig.camera.kind.value,
                          "rig_file": rig.source},
        rig_sha256=rig.sha256,
    )
    if session.complete:
        log.info("%s is already complete (%d frames); nothing to do", out, session.done)
        return session.finish()
    try:
        with Rig(rig) as opened:
            if not resume:
                session.writer.doc["pixel_size_mm"] = opened.pixel_size_mm
                session.writer.doc["optics"] = opened.optics
            return session.run(opened.stage, opened.camera, progress=progress)
    except BaseException:
        session.discard_if_empty()  # a failed run leaves no empty --out behind
        raise
