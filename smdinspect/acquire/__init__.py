"""Acquisition: a serial motion stage, cameras, and the focal sweep that writes a stack.

The pieces, each behind a small interface:

* :class:`Stage` - a z axis in machine mm; :class:`GrblStage` speaks GRBL 1.1 over any
  pyserial URL; :class:`FakeGrbl` is a GRBL controller simulated on a real pty;
* :class:`Camera` - ``capture() -> (frame, metadata)``: :class:`OpenCVCamera`,
  :class:`FolderCamera`, :class:`SimulatedCamera`, :class:`GenICamCamera`;
* :func:`run_sweep` - move, settle, read back z, capture, write atomically; resumable;
* :func:`load_rig` / :func:`acquire` - the TOML rig file and the one-call sweep the
  ``smdinspect acquire`` command runs.
"""

from ._camera import (
    Camera,
    FolderCamera,
    GenICamCamera,
    OpenCVCamera,
    SimulatedCamera,
    capture_average,
)
from ._fake_grbl import FAULT_KINDS, FakeGrbl
from ._grbl import ALARM_MEANINGS, ERROR_MEANINGS, GrblStage, parse_status
from ._rig import CameraConfig, CameraKind, Rig, RigConfig, acquire, load_rig, parse_rig
from ._stage import Stage, StageConfig, StageProtocol, StageStatus
from ._sweep import MAX_FRAMES, SweepConfig, SweepResult, ZMapping, run_sweep

__all__ = [
    "ALARM_MEANINGS",
    "Camera",
    "CameraConfig",
    "CameraKind",
    "ERROR_MEANINGS",
    "FAULT_KINDS",
    "FakeGrbl",
    "FolderCamera",
    "GenICamCamera",
    "GrblStage",
    "MAX_FRAMES",
    "OpenCVCamera",
    "Rig",
    "RigConfig",
    "SimulatedCamera",
    "Stage",
    "StageConfig",
    "StageProtocol",
    "StageStatus",
    "SweepConfig",
    "SweepResult",
    "ZMapping",
    "acquire",
    "capture_average",
    "load_rig",
    "parse_rig",
    "parse_status",
    "run_sweep",
]
