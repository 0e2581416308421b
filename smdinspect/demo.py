"""``smdinspect demo``: the whole pipeline on a synthetic board, no hardware needed.

1. A synthetic demo board (``references/demo_board.json``) with a few injected defects,
   placed slightly shifted and rotated in the field of view.
2. A focal sweep through the *simulated rig*: a fake GRBL controller on a real
   pseudo-terminal, driven over pyserial exactly like a real stage, and a simulated camera
   that renders the board at the height the stage reports.
3. Reconstruction (shape from focus), registration to the reference board, a verdict per
   joint, and the reports (JSON, CSV, JUnit, HTML), point cloud and mesh.
"""

from __future__ import annotations

import json
import logging
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from .errors import InputError

__all__ = ["DEMO_DEFECTS", "DemoResult", "demo_board_path", "run_demo"]

log = logging.getLogger(__name__)

#: Defects the demo injects (joint id → class).
DEMO_DEFECTS = {"R1.2": "insufficient", "C1.1": "excess", "U1.6": "bridge", "R2.1": "missing"}
MARKER = ".smdinspect-demo"

Progress = Callable[[str, int, int], None]


def demo_board_path() -> Path:
    """The demo board file shipped with smdinspect."""
    here = Path(__file__).resolve().parent
    for p in (here.parent / "references" / "demo_board.json", here / "data" / "demo_board.json"):
        if p.is_file():
            return p
    raise InputError("the demo board file (references/demo_board.json) is missing from this install")


@dataclass(frozen=True)
class DemoResult:
    """What the demo produced."""

    out: Path
    stack_dir: Path
    report_dir: Path
    labels: dict
    inspection: object  # smdinspect.inspect.InspectionResult
    seconds: dict


def _rig_text(board: Path, defects: dict[str, str], *, seed: int, pixel_size_mm: float,
              offset_mm: tuple[float, float], rotate_deg: float, top_mm: float) -> str:
    spec = ",".join(f"{k}:{v}" for k, v in defects.items())
    return f"""
[stage]
protocol = "grbl"
boot_wait_s = 0.0
timeout_s = 5.0
z_min_mm = -10.0
z_max_mm = 0.0
feed_mm_min = 1200.0
poll_interval_s = 0.005

[stage.fake]
steps_per_mm = 400.0
max_rate_mm_s = 40.0
start_z_mm = 0.0

[mapping]
focus_offset_mm = 5.0
direction = 1

[camera]
kind = "simulated"
board = {json.dumps(str(board))}
defects = {json.dumps(spec)}
seed = {seed}
sensor = "normal"

[camera.scene_options]
pixel_size_mm = {pixel_size_mm}
offset_mm = [{offset_mm[0]}, {offset_mm[1]}]
rotate_deg = {rotate_deg}

[optics]
focal_length_mm = 50.0
pixel_pitch_mm = 0.015

[sweep]
z_start_mm = -0.15
z_stop_mm = {top_mm + 0.15:.3f}
step_mm = 0.05
settle_s = 0.0
backlash_mm = 0.1
frames_per_step = 1
"""


def run_demo(
    out: str | Path = "smdinspect-demo",
    *,
    seed: int = 7,
    defects: dict[str, str] | None = None,
    pixel_size_mm: float = 0.02,
    progress: Progress | None = None,
) -> DemoResult:
    """Simulate, sweep, reconstruct and inspect the demo board into ``out``.

    ``out`` is replaced if an earlier demo made it; any other non-empty folder is refused.

    Parameters
    ----------
    out : path
    seed : int
        Placement, textures and sensor noise.
    defects : dict, optional
        Joint id → defect class (default :data:`DEMO_DEFECTS`).
    pixel_size_mm : float
    progress : callable(stage, done, total), optional
        ``stage`` is ``"sweep"`` or ``"reconstruct"``.
    """
    from .acquire import acquire, parse_rig
    from .inspect import load_board
    from .pipeline import inspect_stack
    from .synth import board_scene

    out = Path(out)
    if out.exists():
        if not out.is_dir():
            raise InputError(f"demo output {out} exists and is not a folder")
        if any(out.iterdir()) and not (out / MARKER).exists():
            raise InputError(f"demo output {out} is a non-empty folder the demo did not make; "
                             "pass another --out")
        shutil.rmtree(out)
    out.mkdir(parents=True)
    (out / MARKER).write_text("made by smdinspect demo; replaced by the next demo run\n")
    defects = dict(DEMO_DEFECTS if defects is None else defects)
    board_file = demo_board_path()
    board = load_board(board_file)
    offset_mm, rotate_deg = (0.6, -0.4), 2.5
    # The truth labels of exactly the scene the simulated camera renders.
    scene, labels = board_scene(board, defects=defects, pixel_size_mm=pixel_size_mm,
                                offset_mm=offset_mm, rotate_deg=rotate_deg, seed=seed)
    (out / "truth").mkdir()
    (out / "truth" / "labels.json").write_text(json.dumps(labels, indent=2))
    rig = parse_rig(_rig_text(board_file, defects, seed=seed, pixel_size_mm=pixel_size_mm,
                              offset_mm=offset_mm, rotate_deg=rotate_deg,
                              top_mm=float(scene.height_mm.max())),
                    base_dir=out, source="smdinspect demo")
    t0 = time.perf_counter()
    stack_dir = out / "stack"
    acquire(rig, stack_dir, progress=(lambda d, t: progress("sweep", d, t)) if progress else None)
    t1 = time.perf_counter()
    report_dir = out / "report"
    result = inspect_stack(stack_dir, board, report_dir,
                           progress=(lambda d, t: progress("reconstruct", d, t)) if progress else None)
    t2 = time.perf_counter()
    return DemoResult(out=out, stack_dir=stack_dir, report_dir=report_dir, labels=labels,
                      inspection=result,
                      seconds={"sweep": round(t1 - t0, 1), "inspect": round(t2 - t1, 1)})
