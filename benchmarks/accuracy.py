"""Accuracy against ground truth on synthetic scenes (prints the README's figures).

* textured cone (512 px at 15 µm/px, 1.6 mm tall, Δd = 50 µm): RMSE on confident pixels
  for each peak fit, in steps Δd;
* demo and dense boards (20 µm/px): coverage, median |error| and RMSE on confident
  pixels, in steps;
* defect-free boards through the whole pipeline (reconstruct + inspect): median of
  measured − true max joint height, chips and gull-wings apart.

    .venv/bin/python benchmarks/accuracy.py
"""

from __future__ import annotations

import statistics
import tempfile
from pathlib import Path

import numpy as np

from smdinspect.optics import Optics
from smdinspect.pipeline import inspect_stack
from smdinspect.sff import FocusConfig, reconstruct
from smdinspect.synth import board_scene, cone_scene, render_stack

ROOT = Path(__file__).resolve().parents[1]
STEP = 0.05


def _sweep(top_mm: float) -> np.ndarray:
    """Frames 3 steps beyond the scene, offset so no true height sits on a frame."""
    return np.round(np.arange(-3 * STEP, top_mm + 3 * STEP, STEP) - 0.0123, 6)[::-1]


def _errors(surface, truth) -> np.ndarray:
    return (surface.height_mm - truth)[surface.reliable] / STEP


def main() -> None:
    with tempfile.TemporaryDirectory(prefix="smdinspect-accuracy-") as tmp:
        tmp = Path(tmp)
        cone = cone_scene(size_px=512, pixel_size_mm=0.015, height_mm=1.6, seed=3)
        stack = render_stack(cone, _sweep(1.6), optics=Optics.for_pixel_size(0.015), seed=5,
                             out=tmp / "cone", previews=False)
        fits = {fit: _errors(reconstruct(stack, FocusConfig(fit=fit)), cone.height_mm)
                for fit in ("power", "gauss3", "lsq", "argmax")}
        print("cone 512 px, 15 um/px, %d frames: RMSE on confident pixels %s" % (
            len(stack), ", ".join(f"{k} {np.sqrt(np.mean(e ** 2)):.3f} step"
                                  for k, e in fits.items())))
        for name, seed in (("demo_board", 5), ("dense_board", 3)):
            board = ROOT / "references" / f"{name}.json"
            scene, labels = board_scene(board, pixel_size_mm=0.02, seed=seed)
            stack = render_stack(scene, _sweep(float(scene.height_mm.max())),
                                 optics=Optics.for_pixel_size(0.02), seed=4,
                                 out=tmp / name, previews=False)
            s = reconstruct(stack, FocusConfig())
            e = _errors(s, scene.height_mm)
            print(f"{name} 20 um/px seed {seed}, SFF defaults: coverage {s.coverage:.3f}, "
                  f"median |error| {np.median(np.abs(e)):.3f} step, RMSE "
                  f"{np.sqrt(np.mean(e ** 2)):.3f} step")
            res = inspect_stack(stack, board, tmp / f"{name}-report")
            truth = {j["id"]: j["true_height_mm"] for j in labels["joints"]}
            errs: dict[str, list[float]] = {"chip_end": [], "gullwing_heel": []}
            for j in res.joints:
                if j.verdict.value != "unreliable" and np.isfinite(j.measured_max_mm):
                    errs[j.termination].append(j.measured_max_mm - truth[j.id])
            alle = errs["chip_end"] + errs["gullwing_heel"]
            print(f"  defect-free, through the pipeline: exit {res.exit_code}, "
                  f"{len(res.unreliable)} of {len(res.joints)} joints unreliable; "
                  f"measured - true max height, median: chips "
                  f"{statistics.median(errs['chip_end']) * 1000:+.0f} um, gull-wings "
                  f"{statistics.median(errs['gullwing_heel']) * 1000:+.0f} um; all |error| "
                  f"{statistics.median(map(abs, alle)) / STEP:.2f} step")


if __name__ == "__main__":
    main()
