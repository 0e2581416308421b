"""Solder by its true slope: how much shape from focus measures, how well, and why not.

On the randomised boards of ``benchmarks/inspection.py`` (same seeds, same rendering,
same ``--cache`` of reconstructed surfaces) every solder pixel (shiny, 0.03–0.8 mm above
the board) is put in a bin of its true surface slope, and each bin reports its share of
reliable pixels, the reasons the others are unreliable (``reason.png``'s), and the
height error (surface − truth, µm) of the reliable pixels and of each reason's. This is
what limits a chip's fillet: its upper part, steeper than ~45°, is where its height is
(README, "Weak spots" of the inspection benchmark).

    .venv/bin/python benchmarks/solder_slopes.py --seeds tuning --first 28 --boards 6 --cache cache/

Only boards seen through a telecentric lens are counted: through an ordinary lens the
aligned surface is not pixel for pixel the scene's height map.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import inspection as bench  # noqa: E402  (also puts the repository on the path)

from smdinspect.sff import UNRELIABLE_REASONS  # noqa: E402
from smdinspect.synth._board_scene import TEST_SEEDS, TUNING_SEEDS  # noqa: E402

#: slope bins (degrees)
BINS = ((0, 20), (20, 40), (40, 55), (55, 70), (70, 90))
#: shininess and height range (mm) that make a pixel solder (the renderer's solder and
#: tin are shiny; the mask, silkscreen and mould are matte)
SOLDER_SPECULAR = 0.5
SOLDER_RANGE_MM = (0.03, 0.8)
#: a reason is listed in a bin when it holds at least this share of the bin's pixels
MIN_SHARE = 0.02


def solder_pixels(scene) -> tuple[np.ndarray, np.ndarray]:
    """(solder mask, true slope in degrees) of a scene."""
    z = scene.height_mm
    gy, gx = np.gradient(z, scene.pixel_size_mm)
    slope = np.degrees(np.arctan(np.hypot(gx, gy)))
    lo, hi = SOLDER_RANGE_MM
    spec = scene.specular if scene.specular is not None else np.zeros_like(z)
    return (spec > SOLDER_SPECULAR) & (z > lo) & (z < hi), slope


def tally(pairs) -> dict:
    """Per slope bin: pixel count, and per reason code (0: reliable) the errors (µm)."""
    out = {b: {"n": 0, "err": {}} for b in BINS}
    for scene, surface in pairs:
        solder, slope = solder_pixels(scene)
        err = (surface.height_mm.astype(np.float64) - scene.height_mm) * 1e3
        for b in BINS:
            sel = solder & (slope >= b[0]) & (slope < b[1])
            out[b]["n"] += int(sel.sum())
            codes = surface.reason[sel]
            e = err[sel]
            for code in np.unique(codes):
                out[b]["err"].setdefault(int(code), []).append(e[codes == code])
    return out


def report(t: dict) -> str:
    lines = ["slope     solder px  reliable  |err| p50/p90 (µm)   unreliable by reason: share, |err| p50"]
    for b in BINS:
        n = t[b]["n"]
        if not n:
            continue
        errs = {c: np.concatenate(v) for c, v in t[b]["err"].items()}
        rel = errs.get(0, np.zeros(0))
        fin = np.abs(rel[np.isfinite(rel)])
        acc = (f"{np.median(fin):5.0f} / {np.percentile(fin, 90):5.0f}" if fin.size
               else "    - /     -")
        why = []
        for code, e in sorted(errs.items(), key=lambda kv: -kv[1].size):
            if code == 0 or e.size < MIN_SHARE * n:
                continue
            f = np.abs(e[np.isfinite(e)])
            med = f"{np.median(f):.0f}" if f.size else "-"
            why.append(f"{UNRELIABLE_REASONS[code][0]} {e.size / n:.0%} ({med})")
        lines.append(f"{b[0]:2d}-{b[1]:2d}°  {n:10d}  {rel.size / n:8.0%}  {acc:>17s}   "
                     + ", ".join(why))
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", choices=("tuning", "test"), default="tuning")
    ap.add_argument("--first", type=int, default=0, help="offset into the seed range")
    ap.add_argument("--boards", type=int, default=4, help="boards per board file")
    ap.add_argument("--board", choices=(*bench.BOARDS, "both"), default="both")
    ap.add_argument("--cache", type=Path, default=None,
                    help="reconstructed surfaces, shared with benchmarks/inspection.py")
    args = ap.parse_args(argv)
    seeds = TEST_SEEDS if args.seeds == "test" else TUNING_SEEDS
    names = list(bench.BOARDS) if args.board == "both" else [args.board]
    pairs, skipped = [], 0
    with tempfile.TemporaryDirectory(prefix="smdinspect-slopes-") as tmp:
        for k in range(args.boards):
            for name in names:
                seed = seeds[args.first + k]
                case, scene, _, surface = bench.board_surface(name, seed, "sff", Path(tmp),
                                                              args.cache)
                if case["lens"] != "telecentric" or surface.reason.shape != scene.height_mm.shape:
                    skipped += 1
                    continue
                pairs.append((scene, surface))
                print(f"  {name} seed {seed}", file=sys.stderr)
    print(f"{len(pairs)} boards ({args.seeds} seeds from {seeds[args.first]}; {skipped} seen "
          f"through an ordinary lens skipped)")
    print(report(tally(pairs)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
