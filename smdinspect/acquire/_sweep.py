"""The focal sweep: move, settle, read back z, capture, write - frame by frame.

For every planned focused-plane height the sweep

1. moves the stage there, always finishing the move in the sweep's direction
   (:meth:`Stage.approach`: overshoot by ``backlash_mm`` and come back when needed);
2. waits for ``Idle``, sleeps ``settle_s``, and reads the machine z back;
3. captures ``frames_per_step`` frames and averages them;
4. writes the frame and an updated ``stack.json`` atomically
   (:class:`smdinspect.stack.StackWriter`) with the **measured** ``z_mm``.

Any failure - an exception or Ctrl-C - sends a feed hold, and leaves the frames written
so far listed in ``stack.json``; ``resume=True`` continues with the next frame. The
manifest's ``meta.rig_sha256`` pins the rig configuration a stack was started with;
resuming with a different one is refused.
"""

from __future__ import annotations

import errno
import logging
import math
import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from ..errors import CameraError, InputError, OutputError, SmdInspectError, StageError
from ._camera import Camera, capture_average
from ._stage import Stage

__all__ = ["MAX_FRAMES", "SweepConfig", "SweepResult", "ZMapping", "run_sweep"]

log = logging.getLogger(__name__)

Progress = Callable[[int, int], None]

#: Default bound on the frames of one sweep (``[sweep] max_frames`` raises it).
MAX_FRAMES = 2000


@dataclass(frozen=True)
class ZMapping:
    """Machine z of the stage ↔ focused-plane height ``z_mm`` above the board.

    ``z_mm = focus_offset_mm + direction * machine_z_mm``

    Parameters
    ----------
    focus_offset_mm : float
        ``z_mm`` of the focused plane when the machine is at z = 0 (calibrate by
        focusing on the bare board: then ``focus_offset_mm = -direction * MPos.z``).
    direction : {1, -1}
        +1 when positive machine z raises the focused plane (the camera rides the z
        axis and +Z is up); -1 when positive machine z lowers it (e.g. the axis lifts
        the board towards the camera, or +Z points down).
    """

    focus_offset_mm: float = 0.0
    direction: int = 1

    def __post_init__(self) -> None:
        if (isinstance(self.focus_offset_mm, bool) or not isinstance(self.focus_offset_mm, (int, float))
                or not math.isfinite(self.focus_offset_mm)):
            raise InputError(f"focus_offset_mm must be a finite number; got {self.focus_offset_mm!r}")
        if self.direction not in (1, -1) or isinstance(self.direction, bool):
            raise InputError(f"mapping direction must be 1 or -1; got {self.direction!r}")

    def z_mm(self, machine_z_mm: float) -> float:
        """Focused-plane height for a machine z."""
        return self.focus_offset_mm + self.direction * machine_z_mm

    def machine_z_mm(self, z_mm: float) -> float:
        """Machine z that puts the focused plane at ``z_mm``."""
        return (z_mm - self.focus_offset_mm) * self.direction


@dataclass(frozen=True)
class SweepConfig:
    """The z range and timing of a sweep (the rig file's ``[sweep]`` table).

    Parameters
    ----------
    z_start_mm, z_stop_mm : float
        First and last focused-plane heights; the sweep runs from start towards stop
        (either way) and includes ``z_stop_mm`` when it falls on the step grid.
    step_mm : float
        Spacing Δd between frames, > 0.
    settle_s : float
        Wait after the stage is Idle before reading z and capturing (vibration).
    backlash_mm : float
        Overshoot distance that takes up the lead screw's slack; 0 disables it.
    frames_per_step : int
        Frames averaged per position.
    max_frames : int
        Refuse a sweep planning more frames than this (default :data:`MAX_FRAMES`): a
        mistyped step must not start hours of capture and fill the disk.
    """

    z_start_mm: float
    z_stop_mm: float
    step_mm: float
    settle_s: float = 0.0
    backlash_mm: float = 0.0
    frames_per_step: int = 1
    max_frames: int = MAX_FRAMES

    def __post_init__(self) -> None:
        for name in ("z_start_mm", "z_stop_mm", "step_mm", "settle_s", "backlash_mm"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise InputError(f"sweep {name} must be a finite number; got {value!r}")
        if self.step_mm <= 0:
            raise InputError(f"sweep step_mm must be > 0; got {self.step_mm}")
        if self.settle_s < 0:
            raise InputError(f"sweep settle_s must be >= 0; got {self.settle_s}")
        if self.backlash_mm < 0:
            raise InputError(f"sweep backlash_mm must be >= 0; got {self.backlash_mm}")
        if (isinstance(self.frames_per_step, bool) or not isinstance(self.frames_per_step, int)
                or self.frames_per_step < 1):
            raise InputError(f"sweep frames_per_step must be an integer >= 1; got "
                             f"{self.frames_per_step!r}")
        if isinstance(self.max_frames, bool) or not isinstance(self.max_frames, int) \
                or self.max_frames < 3:
            raise InputError(f"sweep max_frames must be an integer >= 3; got {self.max_frames!r}")
        planned = abs(self.z_stop_mm - self.z_start_mm) / self.step_mm + 1
        if not planned <= self.max_frames + 1e-6:
            raise InputError(
                f"sweep from z_start_mm={self.z_start_mm} to z_stop_mm={self.z_stop_mm} in "
                f"steps of {self.step_mm} mm plans {planned:.3g} frames, more than max_frames = "
                f"{self.max_frames}; check step_mm, or raise max_frames in [sweep]")
        if self.n_frames < 3:
            raise InputError(
                f"sweep from z_start_mm={self.z_start_mm} to z_stop_mm={self.z_stop_mm} in "
                f"steps of {self.step_mm} mm gives {self.n_frames} frame(s); a stack needs >= 3"
            )

    @property
    def n_frames(self) -> int:
        """Number of planned frames."""
        return int(math.floor(abs(self.z_stop_mm - self.z_start_mm) / self.step_mm + 1e-6)) + 1

    @property
    def sign(self) -> int:
        """+1 when the sweep runs towards larger ``z_mm``, else -1."""
        return 1 if self.z_stop_mm >= self.z_start_mm else -1

    def z_positions_mm(self) -> np.ndarray:
        """``(n_frames,) float64`` planned focused-plane heights, in sweep order."""
        i = np.arange(self.n_frames, dtype=np.float64)
        return self.z_start_mm + self.sign * self.step_mm * i


@dataclass(frozen=True)
class SweepResult:
    """What a sweep left on disk.

    Attributes
    ----------
    root : Path
        The stack directory.
    z_mm : (n_frames,) float64
        Measured focused-plane heights of all frames, acquisition order.
    n_new : int
        Frames written by this run (the rest came from an earlier, interrupted run).
    complete : bool
        All planned frames are on disk.
    elapsed_s : float
    """

    root: Path
    z_mm: np.ndarray = field(repr=False)
    n_new: int
    complete: bool
    elapsed_s: float

    @property
    def n_frames(self) -> int:
        return int(self.z_mm.size)


def run_sweep(
    stage: Stage,
    camera: Camera,
    out: str | Path,
    *,
    sweep: SweepConfig,
    mapping: ZMapping = ZMapping(),
    resume: bool = False,
    pixel_size_mm: float | None = None,
    optics: dict[str, Any] | None = None,
    rig: dict[str, Any] | None = None,
    rig_sha256: str = "",
    progress: Progress | None = None,
) -> SweepResult:
    """Sweep the focus through ``sweep`` and write a stack to ``out``.

    Parameters
    ----------
    stage : Stage
        An open stage.
    camera : Camera
        An open camera.
    out : path
        Stack directory. Must not hold a stack yet, unless ``resume``.
    sweep : SweepConfig
    mapping : ZMapping
        Machine z ↔ ``z_mm``.
    resume : bool
        Continue the stack in ``out`` after its last complete frame.
    pixel_size_mm : float, optional
        Object-side pixel size stored in ``stack.json``.
    optics, rig : dict, optional
        Stored in ``stack.json`` (``rig`` is completed with the sweep's parameters).
    rig_sha256 : str
        Fingerprint of the rig configuration; stored in ``meta`` and compared on resume.
    progress : callable(done, total), optional

    Returns
    -------
    SweepResult

    Raises
    ------
    InputError
        ``out`` already holds a stack (without ``resume``), nothing to resume, or the
        rig changed since the stack was started.
    StageError, CameraError
        Hardware failures; a feed hold is sent and the frames so far are kept.
    OutputError
        No space left on the device; frames so far are kept.
    OSError
        Not writable; frames so far are kept.
    """
    session = _Session.prepare(out, sweep=sweep, mapping=mapping, resume=resume,
                               pixel_size_mm=pixel_size_mm, optics=optics, rig=rig,
                               rig_sha256=rig_sha256)
    return session.run(stage, camera, progress=progress)


# ---------------------------------------------------------------------------------------
# temp files of an interrupted atomic write (frame or manifest), and frame files
_STRAY = re.compile(r"^(?:\.frame_\d+\..+|\.stack\..+\.json|frame_(\d+)\.(?:png|tiff))$")


class _Session:
    """The writer side of a sweep; prepared before any hardware is touched."""

    def __init__(self) -> None:
        self.writer: Any = None
        self.sweep: SweepConfig
        self.mapping: ZMapping
        self.done = 0
        self.ref: tuple[tuple[int, ...], np.dtype] | None = None
        self.made: list[Path] = []  # folders this session created, outermost first

    @classmethod
    def prepare(cls, out: str | Path, *, sweep: SweepConfig, mapping: ZMapping, resume: bool,
                pixel_size_mm: float | None, optics: dict[str, Any] | None,
                rig: dict[str, Any] | None, rig_sha256: str) -> "_Session":
        from ..stack import MANIFEST, StackWriter, read_image

        if not isinstance(sweep, SweepConfig):
            raise InputError(f"sweep must be a SweepConfig; got {type(sweep).__name__}")
        if not isinstance(mapping, ZMapping):
            raise InputError(f"mapping must be a ZMapping; got {type(mapping).__name__}")
        self = cls()
        self.sweep, self.mapping = sweep, mapping
        root = Path(out)
        manifest = root / MANIFEST
        if root.exists() and not root.is_dir():
            raise InputError(f"--out {root} exists and is not a directory")
        if not resume:
            if manifest.exists():
                raise InputError(f"{root} already holds a stack ({MANIFEST}); pass --resume to "
                                 "continue it or choose another --out")
            rig_block = {
                **(rig or {}),
                "step_mm": sweep.step_mm,
                "z_start_mm": sweep.z_start_mm,
                "z_stop_mm": sweep.z_stop_mm,
                "settle_s": sweep.settle_s,
                "backlash_mm": sweep.backlash_mm,
                "frames_per_step": sweep.frames_per_step,
                "focus_offset_mm": mapping.focus_offset_mm,
                "direction": mapping.direction,
            }
            meta = {"rig_sha256": rig_sha256, "planned_frames": sweep.n_frames,
                    "complete": False, "acquired_by": "smdinspect acquire"}
            self.made = [p for p in (root, *root.parents) if not p.exists()][::-1]
            self.writer = StackWriter(root, pixel_size_mm=pixel_size_mm, optics=optics,
                                      rig=rig_block, meta=meta)
            return self
        if not manifest.is_file():
            raise InputError(f"nothing to resume: {root} has no {MANIFEST}; run without --resume")
        writer = StackWriter.resume(root)
        meta = writer.doc["meta"]
        old = meta.get("rig_sha256")
        if old is None:
            raise InputError(f"cannot resume {root}: its {MANIFEST} was not written by "
                             "'smdinspect acquire' (no rig fingerprint)")
        if old != rig_sha256:
            raise InputError(
                f"cannot resume {root}: the rig file (stage, camera, optics or sweep) changed "
                f"since this stack was started (rig fingerprint {str(old)[:12]} then, "
                f"{rig_sha256[:12]} now); restore it or start a new --out"
            )
        frames = writer.frames
        if len(frames) > sweep.n_frames:
            raise InputError(f"cannot resume {root}: it holds {len(frames)} frames but the rig "
                             f"plans {sweep.n_frames}")
        for i, entry in enumerate(frames):
            if not (root / entry["file"]).is_file():
                raise InputError(f"cannot resume {root}: frame {entry['file']} listed in "
                                 f"{MANIFEST} is missing")
            try:
                image = read_image(root / entry["file"])
            except InputError as exc:
                # written atomically, so damaged later: take it, and the frames after it, again
                log.warning("%s; taking frames %d..%d again", exc, i, len(frames) - 1)
                del frames[i:]
                break
            if self.ref is None:
                self.ref = (image.shape, image.dtype)
            elif (image.shape, image.dtype) != self.ref:
                raise InputError(f"cannot resume {root}: frame {entry['file']} is "
                                 f"{_describe(image.shape, image.dtype)} but the first frame is "
                                 f"{_describe(*self.ref)}")
        self.writer = writer
        self.done = len(frames)
        self._remove_strays(root)
        log.info("resuming %s after %d of %d frames", root, self.done, sweep.n_frames)
        return self

    def _remove_strays(self, root: Path) -> None:
        """Delete temp files of a killed run and frames written but never listed."""
        for p in root.iterdir():
            m = _STRAY.match(p.name)
            if m and (m.group(1) is None or int(m.group(1)) >= self.done):
                log.info("removing leftover %s", p.name)
                p.unlink(missing_ok=True)

    # -- the loop ---------------------------------------------------------------------
    def run(self, stage: Stage, camera: Camera, *, progress: Progress | None) -> SweepResult:
        t0 = time.monotonic()
        sweep, mapping, writer = self.sweep, self.mapping, self.writer
        z_plan = sweep.z_positions_mm()
        machine_plan = [mapping.machine_z_mm(z) for z in z_plan]
        direction = 1 if machine_plan[-1] > machine_plan[0] else -1
        total = sweep.n_frames
        for m in machine_plan:
            stage.check_limits(m)
        if sweep.backlash_mm > 0:
            stage.check_limits(machine_plan[self.done if self.done < total else 0]
                               - direction * sweep.backlash_mm)
        start = self.done
        if progress is not None:
            progress(start, total)
        camera.seek(start * sweep.frames_per_step)
        try:
            for i in range(start, total):
                self._one_frame(i, z_plan[i], machine_plan[i], direction, stage, camera)
                if progress is not None:
                    progress(i + 1, total)
        except BaseException as exc:
            stage.stop()
            self.discard_if_empty()
            kept = len(writer.frames)
            log.info("sweep stopped after %d of %d frames (%s); feed hold sent", kept, total,
                     type(exc).__name__)
            if isinstance(exc, SmdInspectError) and not isinstance(exc, OutputError) and kept:
                raise type(exc)(f"{exc} [{kept} of {total} frames kept in {writer.root}; "
                                "fix the cause and run again with --resume]") from exc
            raise
        return self.finish(n_new=total - start, t0=t0)

    def discard_if_empty(self) -> None:
        """Remove the folders this session created while they hold no frame."""
        if self.writer is None or self.writer.frames:
            return
        for folder in reversed(self.made):
            try:
                folder.rmdir()
            except OSError:
                return

    @property
    def complete(self) -> bool:
        return self.done >= self.sweep.n_frames

    def finish(self, *, n_new: int = 0, t0: float | None = None) -> SweepResult:
        """Mark the stack complete in its manifest and describe it."""
        writer = self.writer
        writer.doc.setdefault("meta", {})["complete"] = True
        writer.write_manifest()
        z = np.array([f["z_mm"] for f in writer.frames], dtype=np.float64)
        elapsed = 0.0 if t0 is None else time.monotonic() - t0
        return SweepResult(root=writer.root, z_mm=z, n_new=n_new, complete=True,
                           elapsed_s=elapsed)

    def _one_frame(self, i: int, z_target: float, machine_target: float, direction: int,
                   stage: Stage, camera: Camera) -> None:
        sweep, writer = self.sweep, self.writer
        stage.approach(machine_target, direction=direction, backlash_mm=sweep.backlash_mm)
        if sweep.settle_s > 0:
            time.sleep(sweep.settle_s)
        machine_z = stage.position()
        # GRBL reports µm; rounding to 1e-9 mm only drops the float noise of the mapping
        z_mm = round(self.mapping.z_mm(machine_z), 9)
        if writer.frames:
            prev = float(writer.frames[-1]["z_mm"])
            if (z_mm - prev) * sweep.sign <= 0:
                raise StageError(
                    f"stage did not advance: frame {i} measured z_mm {z_mm:.4f} is not beyond "
                    f"the previous frame's {prev:.4f} (step smaller than the motor resolution?)"
                )
        frame, meta = capture_average(camera, sweep.frames_per_step)
        if self.ref is None:
            self.ref = (frame.shape, frame.dtype)
        elif (frame.shape, frame.dtype) != self.ref:
            raise CameraError(
                f"camera returned a {_describe(frame.shape, frame.dtype)} frame at frame {i}; "
                f"earlier frames are {_describe(*self.ref)}"
            )
        extra = {"machine_z_mm": machine_z, "target_z_mm": round(float(z_target), 9), "step": i}
        for key in ("exposure", "gain", "exposure_us", "gain_db", "source", "n_averaged"):
            if key in meta and isinstance(meta[key], (int, float, str)):
                extra[key] = meta[key]
        try:
            writer.add_frame(frame, z_mm, **extra)
        except OSError as exc:
            writer.frames[:] = writer.frames[:i]  # the manifest on disk never listed it
            if exc.errno == errno.ENOSPC:
                raise OutputError(errno.ENOSPC, f"no space left on device: {writer.root} "
                                  f"(frame {i}); the {i} frames before it are kept: free space "
                                  "and run again with --resume") from None
            raise
        log.debug("frame %d: z_mm %.4f (machine %.4f)", i, z_mm, machine_z)


def _describe(shape: tuple[int, ...], dtype: np.dtype) -> str:
    size = f"{shape[1]}x{shape[0]}"
    kind = "RGB" if len(shape) == 3 else "grey"
    return f"{size} {kind} {np.dtype(dtype).name}"
