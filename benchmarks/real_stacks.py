"""Benchmark of the SFF core on the three real focal stacks in ``../shared/data``.

For each stack (``pcb-oblique``, ``metal-bore``, ``flat-target-zknown``) it prints, next to
the issue's goal and PASS/FAIL: reliable coverage of the aligned field, outliers against a
robust local surface, agreement of an even-frames-only run with the full run, terracing of
the fractional frame position, (flat target only) plane and quadratic fits of the flat
target, and wall time of ``reconstruct()`` and of the ``smdinspect reconstruct`` command.

    .venv/bin/python benchmarks/real_stacks.py [--stacks pcb-oblique,metal-bore]
        [--repeat 5] [--json out.json] [--pictures DIR] [--quick] [--data DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from smdinspect.sff import FocusConfig, reconstruct, render_height_png, render_reason_map
from smdinspect.sff._depth import masked_gradient
from smdinspect.stack import FocalStack

REPO = Path(__file__).resolve().parents[1]
_SCRIPT = REPO / ".venv" / "bin" / "smdinspect"
#: the command; in a git worktree without a .venv, this interpreter with -m (run it
#: with PYTHONPATH set to the worktree)
CLI = [str(_SCRIPT)] if _SCRIPT.exists() else [sys.executable, "-m", "smdinspect"]

#: name -> (file glob, step_mm for a plain image list; None: z from the file name)
STACKS = {
    "pcb-oblique": ("pcb_*.jpg", -0.5),
    "metal-bore": ("image*.jpg", -0.1),  # rim sharp first: focus moves down
    "flat-target-zknown": ("XP005_Z-*.jpg", None),
}
#: the z in flat-target-zknown's file names (as the README's --z-from-name)
Z_FROM_NAME = r"Z(-?[0-9.]+)"
#: physical height range (mm) stated by a stack's README; none of the three states one,
#: so the out-of-range check uses the swept range only.
SCENE_RANGE_MM: dict[str, tuple[float, float]] = {}


def open_real_stack(folder: Path, pattern: str, step_mm: float | None) -> tuple[FocalStack, list[Path], float]:
    """Build the stack for one data folder; also return its files and the CLI step."""
    paths = sorted(folder.glob(pattern))
    if step_mm is not None:
        return FocalStack.from_images(paths, step_mm=step_mm), paths, step_mm
    # XP005_Z-020.jpg is machine z = -20 mm; the focused plane is z + const, so z works.
    return FocalStack.from_named_images(paths, pattern=Z_FROM_NAME), paths, -1.0


def local_median(height: np.ndarray, mask: np.ndarray, block_px: int) -> np.ndarray:
    """Median of the ``mask`` heights in each ``block_px`` square, upsampled to (H, W).

    Blocks with fewer than max(9, 2 % of the block) masked pixels get NaN (no robust
    local surface there).
    """
    h, w = height.shape
    gh, gw = -(-h // block_px), -(-w // block_px)
    pad = np.full((gh * block_px, gw * block_px), np.inf, np.float32)
    pad[:h, :w] = np.where(mask, height, np.inf)
    blocks = pad.reshape(gh, block_px, gw, block_px).transpose(0, 2, 1, 3).reshape(gh, gw, -1)
    blocks = np.sort(blocks, axis=2)  # masked-out pixels (inf) sort last
    count = np.isfinite(blocks).sum(axis=2)
    med = np.take_along_axis(blocks, np.maximum(count - 1, 0)[..., None] // 2, axis=2)[..., 0]
    med[count < max(9, 0.02 * block_px**2)] = np.nan
    return np.repeat(np.repeat(med, block_px, 0), block_px, 1)[:h, :w]


def robust_fit(x: np.ndarray, y: np.ndarray, z: np.ndarray, *, quadratic: bool):
    """Least squares z ~ [1, x, y(, x², xy, y²)], dropping points > 3·MAD (σ-scaled) away.

    Returns the coefficients and the inlier mask.
    """
    cols = [np.ones_like(x), x, y] + ([x * x, x * y, y * y] if quadratic else [])
    a = np.column_stack(cols)
    keep = np.ones(z.size, bool)
    for _ in range(10):
        coef = np.linalg.lstsq(a[keep], z[keep], rcond=None)[0]
        r = z - a @ coef
        mad = 1.4826 * np.median(np.abs(r[keep] - np.median(r[keep])))
        new = np.abs(r - np.median(r[keep])) <= 3 * max(mad, 1e-9)
        if np.array_equal(new, keep):
            break
        keep = new
    return coef, keep


def flat_figures(surface, field: np.ndarray) -> dict:
    """Tilt, quadratic sag and residual RMS (mm) of the reliable heights of a flat target."""
    h, w = surface.shape
    side = max(h, w)
    rows, cols = np.nonzero(field)
    cx, cy = cols.mean(), rows.mean()
    fx, fy = (cols - cx) / side, (rows - cy) / side  # every field pixel
    sel = surface.reliable[rows, cols]
    x, y, z = fx[sel], fy[sel], surface.height_mm[rows, cols][sel].astype(np.float64)
    plane, keep_p = robust_fit(x, y, z, quadratic=False)
    quad, keep_q = robust_fit(x, y, z, quadratic=True)
    tilt = plane[1] * fx + plane[2] * fy
    sag = quad[3] * fx * fx + quad[4] * fx * fy + quad[5] * fy * fy
    res_p = z - (plane[0] + plane[1] * x + plane[2] * y)
    res_q = z - (quad[0] + quad[1] * x + quad[2] * y + quad[3] * x * x + quad[4] * x * y + quad[5] * y * y)
    return {
        "pixels": int(z.size),
        "tilt_mm": float(np.ptp(tilt)),
        "plane_rms_mm": float(np.sqrt(np.mean(res_p[keep_p] ** 2))),
        "plane_inliers": float(keep_p.mean()),
        "sag_mm": float(np.ptp(sag)),
        "quadratic_rms_mm": float(np.sqrt(np.mean(res_q[keep_q] ** 2))),
        "quadratic_inliers": float(keep_q.mean()),
    }


def figures(name: str, full, even, field: np.ndarray) -> dict:
    """Every quality figure of one stack from its full and even-frames surfaces."""
    z = full.z_mm
    step = float(np.median(np.diff(z)))
    h, w = full.shape
    rel = full.reliable & field
    height = full.height_mm
    n_rel = max(int(rel.sum()), 1)
    out = {"frames": int(z.size), "size_px": [w, h], "step_mm": step,
           "field_share": float(field.mean()), "coverage": float(rel.sum() / max(field.sum(), 1))}

    block = max(3, round(max(h, w) / 40))
    local = local_median(height, rel, block)
    judged = rel & np.isfinite(local)
    local_out = judged & (np.abs(height - local) > 3 * step)
    lo, hi = SCENE_RANGE_MM.get(name, (z[0], z[-1]))
    range_out = rel & ((height < lo - step) | (height > hi + step))
    out.update(outliers_local=float(local_out.sum() / n_rel),
               outliers_range=float(range_out.sum() / n_rel),
               outliers=float((local_out | range_out).sum() / n_rel),
               outliers_unjudged=float((rel & ~judged).sum() / n_rel), outlier_block_px=block)

    both = rel & even.reliable
    diff = np.abs(height[both] - even.height_mm[both]) / step
    out["even_median_steps"] = float(np.median(diff)) if diff.size else float("nan")
    out["even_agree_field"] = float((diff <= 0.25).sum() / max(field.sum(), 1))

    frames = np.interp(height, z, np.arange(z.size)).astype(np.float32)
    t = frames[rel] % 1.0
    hist = np.histogram(t, bins=10, range=(0.0, 1.0))[0] / max(t.size, 1)
    out["terrace_hist"] = [round(float(s), 4) for s in hist]
    out["terrace_dev"] = float(np.max(np.abs(hist - 0.1)) / 0.1)
    # The same split by the local slope (frames per px, 8-px scale): a surface sloping
    # through the frames must fill every fractional position alike; a flat part of the
    # scene puts all its pixels at its own one, with or without terraces
    gx, gy, dense = masked_gradient(frames, rel, sigma_px=8.0, min_weight=0.5)
    slope = np.hypot(gx, gy)
    for key, sel in (("flat", rel & dense & (slope < 0.005)), ("sloped", rel & dense & (slope >= 0.02))):
        ts = frames[sel] % 1.0
        hs = np.histogram(ts, bins=10, range=(0.0, 1.0))[0] / max(ts.size, 1)
        out[f"terrace_dev_{key}"] = float(np.max(np.abs(hs - 0.1)) / 0.1) if ts.size else float("nan")
        out[f"terrace_share_{key}"] = float(sel.sum() / n_rel)
    # where the coverage goes: peaks beyond the sweep (sharpest on an end frame, clearly
    # textured) cannot be measured by any focus measure of these frames
    if full.beyond is not None:
        beyond = (full.beyond != 0) & field
        out["beyond_share"] = float(beyond.sum() / max(field.sum(), 1))
        out["coverage_within_sweep"] = float(rel.sum() / max((field & ~beyond).sum(), 1))
    reasons = full.unreliable_reasons()
    if reasons is not None:  # shares of the image, largest first
        out["unreliable_reasons"] = {k: round(v, 4) for k, v in reasons.items()}
    if name == "flat-target-zknown":
        out["flat"] = flat_figures(full, field)
    return out


#: Runs argv[2:] with stdout to /dev/null and stderr to argv[1]; prints
#: "rc wall_s user_s sys_s maxrss_kib". A fresh launcher process is needed because on
#: Linux a child's ru_maxrss starts at the RSS of the process it was forked from (here
#: this benchmark, ~1 GB after a reconstruction).
LAUNCHER = """import os, sys, time
acts = [(os.POSIX_SPAWN_OPEN, 1, os.devnull, os.O_WRONLY, 0),
        (os.POSIX_SPAWN_OPEN, 2, sys.argv[1], os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)]
t0 = time.perf_counter()
pid = os.posix_spawn(sys.argv[2], sys.argv[2:], os.environ, file_actions=acts)
_, status, usage = os.wait4(pid, 0)
print(os.waitstatus_to_exitcode(status), time.perf_counter() - t0, usage.ru_utime,
      usage.ru_stime, usage.ru_maxrss)
"""


def time_process(cmd: list[str], repeat: int) -> dict:
    """Whole-process figures of ``cmd`` (imports, reading, writing), one fresh process a run.

    Returns the medians over ``repeat`` runs of the wall time (s), the CPU time (user +
    system, s) and the peak RSS (MiB), every run's figures, and the machine's 1-minute
    load average before each run (the machine may be shared: quote it with the times).
    """
    walls, cpus, rss, loads = [], [], [], []
    for _ in range(repeat):
        with tempfile.TemporaryDirectory(prefix="smd-bench-") as tmp:
            err = Path(tmp) / "stderr.txt"
            loads.append(os.getloadavg()[0])
            done = subprocess.run([sys.executable, "-c", LAUNCHER, str(err),
                                   *[c.replace("{tmp}", tmp) for c in cmd]],
                                  capture_output=True, text=True, check=True)
            rc, wall_s, user_s, sys_s, maxrss_kib = done.stdout.split()
            if int(rc) != 0:
                tail = err.read_text().strip().splitlines()[-1:] or ["(no output)"]
                raise RuntimeError(f"{Path(cmd[0]).name} exited {rc}: {tail[0]}")
            walls.append(float(wall_s))
            cpus.append(float(user_s) + float(sys_s))
            rss.append(int(maxrss_kib) / 1024)  # Linux: KiB
    return {"wall_s": statistics.median(walls), "cpu_s": statistics.median(cpus),
            "peak_mib": statistics.median(rss), "runs": repeat, "walls_s": walls,
            "peaks_mib": rss, "load_1min": loads}


def describe_process(t: dict) -> str:
    """One line: medians of wall, CPU and peak RSS, the run count and the load range."""
    return (f"wall {t['wall_s']:.2f} s, CPU {t['cpu_s']:.2f} s, peak RSS {t['peak_mib']:.0f} MiB "
            f"(medians of {t['runs']}; wall {min(t['walls_s']):.2f}-{max(t['walls_s']):.2f} s; "
            f"load {min(t['load_1min']):.1f}-{max(t['load_1min']):.1f})")


def time_cli(paths: list[Path], step_mm: float, config: FocusConfig, repeat: int) -> dict:
    """Whole-process figures of ``smdinspect reconstruct`` (see :func:`time_process`).

    The CLI gets ``config``'s operator, window, fit and workers, since its defaults may
    differ from ``FocusConfig``'s (``threshold`` and ``edge_jump_steps`` have no flags).
    """
    c = config.to_dict()
    options = [f"--{k.replace('_', '-')}={c[k]}" for k in
               ("operator", "window_px", "fit", "fit_half_width", "min_confidence", "workers")]
    cmd = [*CLI, "reconstruct", *map(str, paths), "--step-mm", str(step_mm),
           *options, "--align", "--out", "{tmp}/out"]
    t = time_process(cmd, repeat)
    return {"cli_s": t["wall_s"], "cli_cpu_s": t["cpu_s"], "cli_peak_mib": t["peak_mib"],
            "cli": t}


def verdict(ok: bool) -> str:
    return "PASS" if ok else "FAIL"


def report(name: str, r: dict) -> None:
    """Print one stack's figures with their goals."""
    w, h = r["size_px"]
    print(f"\n{name}: {r['frames']} frames {w}x{h} px, step {r['step_mm']:g} mm, "
          f"field {100 * r['field_share']:.1f} % of the image")
    rows = [
        ("reliable coverage of field", f"{100 * r['coverage']:.1f} %", ">= 80 %", r["coverage"] >= 0.80),
        (f"outliers (local {r['outlier_block_px']} px >3 Δd | range)",
         f"{100 * r['outliers']:.2f} % ({100 * r['outliers_local']:.2f} | {100 * r['outliers_range']:.2f})",
         "<= 0.5 %", r["outliers"] <= 0.005),
        ("even frames: median |Δ|", f"{r['even_median_steps']:.3f} Δd", "<= 0.25 Δd",
         r["even_median_steps"] <= 0.25),
        ("even frames: agree <= 0.25 Δd", f"{100 * r['even_agree_field']:.1f} % of field", ">= 60 %",
         r["even_agree_field"] >= 0.60),
        ("terraces: max |share-0.1|/0.1", f"{r['terrace_dev']:.2f}", "<= 0.50", r["terrace_dev"] <= 0.5),
    ]
    for label, value, goal, ok in rows:
        print(f"  {label:<36} {value:<24} goal {goal:<11} {verdict(ok)}")
    print("  terrace histogram (t = 0.0..1.0): " + " ".join(f"{s:.3f}" for s in r["terrace_hist"]))
    print(f"  by local slope: flat (< 0.005 frames/px, {100 * r['terrace_share_flat']:.0f} % of "
          f"reliable) {r['terrace_dev_flat']:.2f}, sloped (>= 0.02, "
          f"{100 * r['terrace_share_sloped']:.1f} %) {r['terrace_dev_sloped']:.2f}")
    if "beyond_share" in r:
        print(f"  {100 * r['beyond_share']:.1f} % of the field is sharpest beyond an end of the "
              f"sweep; coverage of the rest {100 * r['coverage_within_sweep']:.1f} %")
    if r.get("unreliable_reasons"):
        print("  unreliable, by reason (reason.png): " + ", ".join(
            f"{k.replace('_', ' ')} {100 * v:.1f} %" for k, v in r["unreliable_reasons"].items()
            if v >= 0.001))
    if r["outliers_unjudged"] > 0:
        print(f"  ({100 * r['outliers_unjudged']:.2f} % of reliable pixels lie in blocks with too few "
              "reliable pixels: not judged)")
    if "flat" in r:
        f = r["flat"]
        print(f"  flat target, {f['pixels']} reliable px: plane tilt {f['tilt_mm']:.3f} mm across "
              f"the field, RMS {f['plane_rms_mm']:.3f} mm ({100 * f['plane_inliers']:.0f} % inliers)")
        print(f"  {'':<20}quadratic sag {f['sag_mm']:.3f} mm, RMS {f['quadratic_rms_mm']:.3f} mm "
              f"({100 * f['quadratic_inliers']:.0f} % inliers)")
    line = f"  time: reconstruct() {r['reconstruct_s']:.2f} s (median of {r['repeat']})"
    if "cli_s" in r:
        line += f"\n  smdinspect reconstruct: {describe_process(r['cli'])}"
    print(line)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--stacks", default=",".join(STACKS), help="comma-separated subset of: %(default)s")
    p.add_argument("--repeat", type=int, default=5, help="timed runs per figure (median; default 5)")
    p.add_argument("--json", type=Path, default=None, help="also write the figures to this file")
    p.add_argument("--pictures", type=Path, default=None, help="save aif.png, height.png and reason.png here")
    p.add_argument("--quick", action="store_true", help="skip the CLI timing")
    p.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    p.add_argument("--operator", default=None, help="focus operator (default: FocusConfig's)")
    p.add_argument("--prefilter", default=None,
                   help="noise pre-filter σ px or 'auto' (default: FocusConfig's, auto)")
    p.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                   help="override a FocusConfig field (repeatable), e.g. --set coarse_factor=8")
    args = p.parse_args(argv)
    names = [s.strip() for s in args.stacks.split(",") if s.strip()]
    unknown = [s for s in names if s not in STACKS]
    if unknown or args.repeat < 1:
        p.error(f"unknown stack(s) {', '.join(unknown)}" if unknown else "--repeat must be >= 1")
    for name in names:
        if not (args.data / name).is_dir():
            print(f"error: data folder not found: {args.data / name}", file=sys.stderr)
            return 2

    overrides = {}
    if args.prefilter is not None:
        overrides["prefilter_px"] = args.prefilter if args.prefilter == "auto" else float(args.prefilter)
    for item in args.set:
        key, sep, value = item.partition("=")
        if not sep or key not in FocusConfig.__dataclass_fields__:
            p.error(f"--set {item}: expected FIELD=VALUE with a FocusConfig field")
        overrides[key] = json.loads(value) if value[:1] in "-0123456789tfn[" else value
    config = FocusConfig(align=True, **({"operator": args.operator} if args.operator else {}),
                         **overrides)
    print(f"load average {' '.join(f'{x:.2f}' for x in os.getloadavg())} on {os.cpu_count()} CPUs; "
          f"config {config.to_dict()}")
    results = {}
    for name in names:
        pattern, step = STACKS[name]
        stack, paths, cli_step = open_real_stack(args.data / name, pattern, step)
        times, full = [], None
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            full = reconstruct(stack, config)
            times.append(time.perf_counter() - t0)
        even_stack = FocalStack(stack.frames[::2], pixel_size_mm=stack.pixel_size_mm)
        even = reconstruct(even_stack, config)
        r = figures(name, full, even, full.field)
        r.update(reconstruct_s=statistics.median(times), repeat=args.repeat,
                 alignment_failures=full.meta.get("alignment", {}).get("failures"))
        if not args.quick:
            r.update(time_cli(paths, cli_step, config, args.repeat))
        if args.pictures is not None:
            out = args.pictures / name
            out.mkdir(parents=True, exist_ok=True)
            aif = full.aif if full.aif.ndim == 2 else cv2.cvtColor(full.aif, cv2.COLOR_RGB2BGR)
            cv2.imwrite(str(out / "aif.png"), aif)
            render_height_png(full, out / "height.png")
            cv2.imwrite(str(out / "reason.png"), render_reason_map(full.reason, full.aif)[:, :, ::-1])
        report(name, r)
        results[name] = r
    load = os.getloadavg()
    print(f"\nload average at the end {' '.join(f'{x:.2f}' for x in load)}")
    if args.json is not None:
        doc = {"load_average": load, "config": config.to_dict(), "stacks": results}
        args.json.write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
