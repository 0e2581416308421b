"""Inspection on randomised boards: per-class recall, right class, false calls.

Every case comes from :func:`smdinspect.synth._board_scene.random_board_case`: about
half the components carry one defect at a severity drawn over a realistic range (lift
0.05–0.4 mm, tilt 5–90°, fillets 0–90 % of the minimum, excess as convex fillets or over
the cap, bridges of varied width and height, shifted and turned parts, missing solder),
on ENIG, HASL or OSP finishes, with or without fiducials, varied lighting, one case in
four seen through an ordinary lens (reconstructed with alignment), one in four cut by
the field edge, each with its own imaging: a pupil 0.35-1.4 times the default (depth of
field 0.06-0.23 mm at 20 um/px), in-focus blur 0.2-0.8 px, a sensor from bright and quiet to small pixels
in poor light, flicker and stage wobble (``--fixed-imaging``: the default optics and
sensor on every board, the suite before 2026-12-04).

Seeds: ``--seeds tuning`` draws from 0–999 (develop the rules on these),
``--seeds test`` from 10000–10999 (the reported figures; never tune on them).

``--mode sff`` renders a focal stack and reconstructs it (the real figure, ~20 s per
board); ``--mode truth`` inspects the true height map with 3 µm noise and 5 % holes (a
quick check of the rules' logic, ~2 s per board).

    .venv/bin/python benchmarks/inspection.py --seeds test --boards 24 --mode sff --out bench/
    .venv/bin/python benchmarks/inspection.py --seeds tuning --first 8 --boards 20 --cache cache/
        # --cache: surfaces kept and reused, so a change to the verdict rules re-runs fast
        # --out: also joints.csv, every joint's label, verdict and raw measurement (the
        # numbers the rules read, e.g. a gull-wing's heel_reach_mm), to study a rule offline

Counted: defects past their IPC-A-610 Class 2 limit (:data:`SEVERITY`) on parts wholly
inside the image. *Recall*: called any defect; *right class*: called a verdict that names
it (its class; ``bridge`` on a bridge's partner; ``missing`` for an insufficient joint
with almost no fillet). *False calls*: good joints called a defect. Joints on parts cut by
the field edge are counted apart: they must be ``unreliable`` or right, and are never
allowed to be ``component_shifted``/``component_missing`` when good. Defects below their
limit (marginal) are reported apart, not counted either way.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import math
import pickle
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from smdinspect.errors import BoardNotLocatedError  # noqa: E402
from smdinspect.inspect import inspect_surface, load_board  # noqa: E402
from smdinspect.synth._board_scene import (  # noqa: E402
    SEVERITY,
    TEST_SEEDS,
    TUNING_SEEDS,
    board_scene,
    case_gather_stack,
    case_imaging,
    random_board_case,
    scene_kwargs,
)

STEP_MM = 0.05
BOARDS = {"demo": ROOT / "references" / "demo_board.json",
          "dense": ROOT / "references" / "dense_board.json"}
GOALS = {"recall": 0.99, "right_class": 0.95, "false_calls": 0, "unreliable": 0.05}
CLASSES = ("missing", "insufficient", "excess", "bridge", "lifted_lead", "tombstone",
           "component_missing", "component_shifted")


def sweep_mm(board) -> np.ndarray:
    """The sweep planned for the tallest thing that may stand on the board: an upright
    chip (its body length) or the tallest body, 3 steps beyond, offset from the grid."""
    top = 0.0
    for c in board.components:
        top = max(top, c.body_height_mm + c.standoff_mm)
        if c.kind == "chip":
            top = max(top, c.body_length_mm + c.standoff_mm)
    return np.round(np.arange(-3 * STEP_MM, top + 3 * STEP_MM, STEP_MM) - 0.0123, 6)[::-1]


def _truth_surface(scene, seed: int):
    from smdinspect.sff import Surface

    rng = np.random.default_rng([seed, 77])
    h = scene.height_mm + rng.normal(0.0, 0.003, scene.height_mm.shape).astype(np.float32)
    reliable = rng.random(h.shape) >= 0.05
    aif = np.round(np.clip(scene.albedo, 0, 1) * 255).astype(np.uint8)
    return Surface(height_mm=h, confidence=reliable.astype(np.float32), reliable=reliable,
                   f_peak=np.ones_like(h), sigma_mm=np.full(h.shape, 0.1, np.float32),
                   reliability_db=np.full(h.shape, 30.0, np.float32), aif=aif,
                   pixel_size_mm=scene.pixel_size_mm,
                   z_mm=np.arange(-0.15, 1.8, STEP_MM))


def _sff_surface(scene, case, tmp: Path, *, fixed_imaging: bool = False,
                 renderer: str = "own"):
    import dataclasses

    from smdinspect.optics import Optics
    from smdinspect.pipeline import inspection_focus_config
    from smdinspect.sff import reconstruct
    from smdinspect.synth import Lighting, render_stack

    if fixed_imaging:
        optics = Optics.for_pixel_size(case["pixel_size_mm"],
                                       telecentric=case["lens"] == "telecentric")
        sensor = None
    else:
        optics, sensor = case_imaging(case)
    z = sweep_mm(case["board"])
    if renderer == "gather":
        stack = case_gather_stack(case, scene, z, tmp, optics=optics, sensor=sensor)
    else:
        stack = render_stack(scene, z, optics=optics, sensor=sensor,
                             lighting=Lighting(**case["lighting"]), seed=case["seed"],
                             out=tmp, previews=False, overwrite=True)
    cfg = inspection_focus_config(case["pixel_size_mm"])
    if case["lens"] == "ordinary":
        cfg = dataclasses.replace(cfg, align=True)
    return reconstruct(stack, cfg)


def board_surface(name: str, seed: int, mode: str, tmp: Path, cache: Path | None = None, *,
                  fixed_imaging: bool = False, renderer: str = "own"):
    """(case, scene, labels, surface) of one randomised board: the surface reconstructed
    from its rendered stack (``mode`` "sff"; kept in and reused from ``cache``) or the
    noisy true height map ("truth")."""
    board = load_board(BOARDS[name])
    case = random_board_case(board, seed)
    scene, labels = board_scene(case["board"], **scene_kwargs(case))
    tag = ("-fixed" if fixed_imaging else "") + ("-gather" if renderer == "gather" else "")
    kept = None if cache is None or mode != "sff" else cache / f"{name}-{seed}{tag}.pkl"
    if kept is not None and kept.exists():
        surface = pickle.loads(kept.read_bytes())
    elif mode == "truth":
        surface = _truth_surface(scene, seed)
    else:
        surface = _sff_surface(scene, case, tmp / f"{name}-{seed}", fixed_imaging=fixed_imaging,
                               renderer=renderer)
        if kept is not None:
            kept.parent.mkdir(parents=True, exist_ok=True)
            part = kept.with_suffix(".part")
            part.write_bytes(pickle.dumps(surface, protocol=5))
            part.replace(kept)
    return case, scene, labels, surface


def run_case(name: str, seed: int, mode: str, tmp: Path, cache: Path | None = None, *,
             fixed_imaging: bool = False, renderer: str = "own") -> dict:
    case, _, labels, surface = board_surface(name, seed, mode, tmp, cache,
                                             fixed_imaging=fixed_imaging, renderer=renderer)
    out = {"board": name, "seed": seed, "lens": case["lens"], "finish": case["finish"],
           "fiducials": case["fiducials"], "edge": case["edge"], "located": True, "joints": []}
    try:
        result = inspect_surface(surface, case["board"])
    except BoardNotLocatedError as exc:
        out["located"] = False
        out["reason"] = str(exc)
        result = None
    if result is not None:
        out["placement"] = placement_error(result.registration.transform,
                                           map_placement(labels, surface), case["board"])
    got = {} if result is None else {j.id: j for j in result.joints}
    for lab in labels["joints"]:
        j = got.get(lab["id"])
        out["joints"].append({
            "id": lab["id"], "class": lab["class"], "accept": lab["accept"],
            "beyond_limit": lab["beyond_limit"], "field": lab["field"],
            "severity": lab["severity"], "true_height_mm": lab["true_height_mm"],
            "verdict": j.verdict.value if j is not None else "not_located",
            "reason": j.reason if j is not None else out.get("reason", ""),
            "measured_max_mm": None if j is None or not math.isfinite(j.measured_max_mm)
            else round(j.measured_max_mm, 4),
            "gap_mm": None if j is None or j.gap_height_mm is None
            or not math.isfinite(j.gap_height_mm) else round(j.gap_height_mm, 4),
            "measured": None if result is None
            else raw_numbers(result.measurements.get(lab["id"]))})
    return out


def map_placement(labels: dict, surface) -> np.ndarray:
    """The true placement in the map's coordinates.

    With the parallax correction (a lens that is not telecentric) an output pixel is
    ``pixel_scale`` times the focused plane's, the frames magnified about the image
    centre c, while map coordinates count from the image corner: the board plane lands
    (1 − pixel_scale) · c · (pixel size / pixel_scale) lower in x and y than the scene
    puts it. Distances are unchanged, so the placement absorbs the shift; the truth is
    shifted alike so that the placement error measures the placement alone."""
    T = np.array(labels["placement"]["board_to_world"], np.float64)
    par = ((surface.meta or {}).get("alignment") or {}).get("parallax") or {}
    if par.get("corrected") and surface.pixel_size_mm:
        ps = float(par["pixel_scale"])
        h, w = surface.height_mm.shape
        T[:2, 2] -= (1.0 - ps) * surface.pixel_size_mm / ps * np.array([(w - 1) / 2, (h - 1) / 2])
    return T


def placement_error(T: np.ndarray, T_true: np.ndarray, board) -> dict:
    """How far the registration's placement ``T`` is from the true one: its rotation
    error (degrees) and the largest displacement of a component's centre (µm)."""
    rot = math.degrees(math.atan2(T[1, 0], T[0, 0]) - math.atan2(T_true[1, 0], T_true[0, 0]))
    worst = max((float(np.hypot(*((T - T_true) @ [c.x_mm, c.y_mm, 1.0])[:2]))
                 for c in board.components), default=0.0)
    return {"rotation_deg": round((rot + 180.0) % 360.0 - 180.0, 4),
            "worst_part_um": round(1000.0 * worst, 1)}


def placement_lines(cases: list[dict]) -> list[str]:
    """The located boards' placement errors against the truth, with and without
    fiducials: |rotation error| median / 90th percentile / max, the worst-placed part
    median / 90th percentile and how many boards have a part > 40 µm off."""
    lines = []
    for fid in (False, True):
        pl = [c["placement"] for c in cases if c.get("placement") and c["fiducials"] == fid]
        if not pl:
            continue
        r = np.abs([p["rotation_deg"] for p in pl])
        w = np.array([p["worst_part_um"] for p in pl])
        lines.append(f"placement vs truth, {len(pl)} boards {'with' if fid else 'without'} "
                     f"fiducials: |rotation error| median {np.median(r):.3f}, p90 "
                     f"{np.percentile(r, 90):.3f}, max {r.max():.3f} deg; worst part median "
                     f"{np.median(w):.0f}, p90 {np.percentile(w, 90):.0f} um, "
                     f"{int((w > 40).sum())} boards > 40 um")
    return lines


def raw_numbers(m) -> dict | None:
    """The scalar fields of a joint's raw measurement (what the verdict rules read),
    rounded; NaN as None."""
    if m is None:
        return None
    out = {}
    for f in dataclasses.fields(m):
        v = getattr(m, f.name)
        if isinstance(v, (bool, int, str)):
            out[f.name] = v
        elif isinstance(v, float):
            out[f.name] = round(v, 5) if math.isfinite(v) else None
    return out


def joint_rows(cases: list[dict]) -> list[dict]:
    """One row per joint of the located boards: the case, the label, the verdict and
    the raw measurement (``measured.*`` columns), for studying a rule offline."""
    rows = []
    for c in cases:
        for j in c["joints"]:
            if not j.get("measured"):
                continue
            row = {"board": c["board"], "seed": c["seed"], "lens": c["lens"],
                   "finish": c["finish"], "id": j["id"], "class": j["class"],
                   "field": j["field"], "severity": json.dumps(j["severity"]),
                   "true_height_mm": j["true_height_mm"], "verdict": j["verdict"]}
            row.update({f"measured.{k}": v for k, v in j["measured"].items()})
            rows.append(row)
    return rows


DEFECT_VERDICTS = set(CLASSES)


def summarise(cases: list[dict]) -> dict:
    per = {c: {"n": 0, "found": 0, "right": 0, "unreliable": 0} for c in CLASSES}
    marginal = {c: {"n": 0, "found": 0} for c in CLASSES}
    good = {"n": 0, "false": 0, "unreliable": 0}
    edge = {"n": 0, "bad": 0, "unreliable": 0}
    judged = {"n": 0, "unreliable": 0}
    false_list, miss_list, edge_list = [], [], []
    not_located = 0
    for case in cases:
        if not case["located"]:
            not_located += 1
        for j in case["joints"]:
            v = j["verdict"]
            tag = f"{case['board']}:{case['seed']}:{j['id']}"
            if j["field"] == "out":
                continue
            if j["field"] == "partial":
                edge["n"] += 1
                edge["unreliable"] += v == "unreliable"
                ok = v in j["accept"] or v == "unreliable"
                if not ok:
                    edge["bad"] += 1
                    edge_list.append(f"{tag} {j['class']} -> {v}")
                continue
            judged["n"] += 1
            judged["unreliable"] += v == "unreliable"
            if j["class"] == "ok":
                if "bridge" in j["accept"]:
                    continue                # a bridge's partner: either verdict is right
                good["n"] += 1
                good["unreliable"] += v == "unreliable"
                if v in DEFECT_VERDICTS or v == "not_located":
                    good["false"] += 1
                    false_list.append(f"{tag} ok -> {v}: {j['reason'][:120]}")
                continue
            bucket = per[j["class"]] if j["beyond_limit"] else marginal[j["class"]]
            bucket["n"] += 1
            found = v in DEFECT_VERDICTS
            bucket["found"] += found
            if j["beyond_limit"]:
                bucket["right"] += v in j["accept"]
                bucket["unreliable"] += v == "unreliable"
                if v not in j["accept"]:
                    miss_list.append(f"{tag} {j['class']} {j['severity']} -> {v}: "
                                     f"{j['reason'][:120]}")
    return {"per_class": per, "marginal": marginal, "good": good, "edge": edge,
            "judged": judged, "false_calls": false_list, "misses": miss_list,
            "edge_calls": edge_list, "not_located": not_located, "boards": len(cases)}


def severity_curves(cases: list[dict], bins: int = 6) -> list[dict]:
    """Detection rate per class against its severity parameter (whole drawn range)."""
    rows = []
    for cls, spec in SEVERITY.items():
        lo, hi = spec["range"]
        edges = np.linspace(lo, hi, bins + 1)
        vals, hits = [], []
        for case in cases:
            for j in case["joints"]:
                if j["class"] != cls or j["field"] != "in" or spec["param"] not in j["severity"]:
                    continue
                vals.append(float(j["severity"][spec["param"]]))
                hits.append(j["verdict"] in DEFECT_VERDICTS)
        vals, hits = np.array(vals), np.array(hits, bool)
        for a, b in zip(edges[:-1], edges[1:]):
            m = (vals >= a) & (vals <= b)
            rows.append({"class": cls, "param": spec["param"], "lo": round(float(a), 4),
                         "hi": round(float(b), 4), "n": int(m.sum()),
                         "detected": float(hits[m].mean()) if m.any() else float("nan"),
                         "limit": spec["limit"]})
    return rows


def report(s: dict) -> str:
    lines = [f"{s['boards']} boards, {s['not_located']} not located"]
    lines.append(f"{'class':<19} {'n':>4} {'recall':>7} {'right':>7} {'unrel':>6}"
                 f"   marginal n / found")
    tot = {"n": 0, "found": 0, "right": 0}
    for c, d in s["per_class"].items():
        n = d["n"]
        for k in tot:
            tot[k] += d[k] if k != "n" else n
        r = d["found"] / n if n else float("nan")
        rc = d["right"] / n if n else float("nan")
        mg = s["marginal"][c]
        lines.append(f"{c:<19} {n:>4} {r:>7.3f} {rc:>7.3f} {d['unreliable']:>6}"
                     f"   {mg['n']:>3} / {mg['found']}")
    n = tot["n"]
    lines.append(f"{'all defects':<19} {n:>4} {tot['found'] / max(n, 1):>7.3f} "
                 f"{tot['right'] / max(n, 1):>7.3f}")
    g, e, jd = s["good"], s["edge"], s["judged"]
    lines.append(f"good joints {g['n']}: false calls {g['false']} "
                 f"({g['false'] / max(g['n'], 1):.3f} per good joint), unreliable {g['unreliable']}")
    lines.append(f"unreliable: {jd['unreliable']} of {jd['n']} judged joints "
                 f"({jd['unreliable'] / max(jd['n'], 1):.1%})")
    lines.append(f"parts at the field edge: {e['n']} joints, {e['unreliable']} unreliable, "
                 f"{e['bad']} wrong calls")
    recall = min((d["found"] / d["n"] for d in s["per_class"].values() if d["n"]), default=float("nan"))
    right = min((d["right"] / d["n"] for d in s["per_class"].values() if d["n"]), default=float("nan"))
    lines.append(f"goals: recall >= {GOALS['recall']} every class (worst {recall:.3f}), right class "
                 f">= {GOALS['right_class']} (worst {right:.3f}), false calls {GOALS['false_calls']} "
                 f"({g['false']}), unreliable <= {GOALS['unreliable']:.0%} "
                 f"({jd['unreliable'] / max(jd['n'], 1):.1%})")
    return "\n".join(lines)


def _plot(rows: list[dict], path: Path) -> None:
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    classes = list(SEVERITY)
    fig, axes = plt.subplots(2, 3, figsize=(12, 6.5))
    for ax, cls in zip(axes.ravel(), classes):
        rr = [r for r in rows if r["class"] == cls]
        x = [(r["lo"] + r["hi"]) / 2 for r in rr]
        y = [r["detected"] for r in rr]
        ax.plot(x, y, "o-")
        for xi, yi, r in zip(x, y, rr):
            ax.annotate(str(r["n"]), (xi, 0.02), ha="center", fontsize=7, color="grey")
        ax.axvline(rr[0]["limit"], color="r", ls="--", lw=1)
        ax.set_ylim(0, 1.05)
        ax.set_title(cls)
        ax.set_xlabel(rr[0]["param"])
        ax.set_ylabel("detected")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _write_csv(path: Path, rows: list[dict]) -> None:
    if not rows:
        return
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", choices=("tuning", "test"), default="tuning")
    ap.add_argument("--first", type=int, default=0, help="offset into the seed range")
    ap.add_argument("--boards", type=int, default=8, help="boards per board file")
    ap.add_argument("--board", choices=(*BOARDS, "both"), default="both")
    ap.add_argument("--mode", choices=("sff", "truth"), default="sff")
    ap.add_argument("--out", type=Path, default=None,
                    help="write cases.json, curves.csv, curves.png and joints.csv (every "
                         "joint's label, verdict and raw measurement)")
    ap.add_argument("--list", action="store_true", help="print every miss and false call")
    ap.add_argument("--cache", type=Path, default=None,
                    help="keep each board's reconstructed surface here and reuse it on the next "
                         "run (to try verdict rules quickly; empty it after changing the SFF "
                         "core or the renderer)")
    ap.add_argument("--fixed-imaging", action="store_true",
                    help="render every board with the default optics and sensor instead of the "
                         "case's drawn pupil, in-focus blur and sensor (the suite before "
                         "2026-12-04)")
    ap.add_argument("--renderer", choices=("own", "gather"), default="own",
                    help="gather: photograph each board with the independent gather model "
                         "(smdinspect.synth._suite.gather_board_stack: another light model, "
                         "a second texture, per-pixel defocus without occlusion, a Gaussian "
                         "or disc PSF, vignetting) instead of our own renderer")
    args = ap.parse_args(argv)
    seeds = TEST_SEEDS if args.seeds == "test" else TUNING_SEEDS
    names = list(BOARDS) if args.board == "both" else [args.board]
    cases = []
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="smdinspect-bench-") as tmp:
        for k in range(args.boards):
            for name in names:
                seed = seeds[args.first + k]
                cases.append(run_case(name, seed, args.mode, Path(tmp), args.cache,
                                      fixed_imaging=args.fixed_imaging,
                                      renderer=args.renderer))
                print(f"  {name} seed {seed}: {time.perf_counter() - t0:.0f} s", file=sys.stderr)
    s = summarise(cases)
    print(f"mode {args.mode}, renderer {args.renderer}, {args.seeds} seeds {seeds[args.first]}..{seeds[args.first + args.boards - 1]}")
    print(report(s))
    for line in placement_lines(cases):
        print(line)
    if args.list:
        for title, key in (("misses", "misses"), ("false calls", "false_calls"),
                           ("field edge", "edge_calls")):
            print(f"-- {title}:")
            for line in s[key]:
                print("  " + line)
    rows = severity_curves(cases)
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "cases.json").write_text(json.dumps(cases, indent=1))
        _write_csv(args.out / "curves.csv", rows)
        _plot(rows, args.out / "curves.png")
        _write_csv(args.out / "joints.csv", joint_rows(cases))
    return 0


if __name__ == "__main__":
    sys.exit(main())
