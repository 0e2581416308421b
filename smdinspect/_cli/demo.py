"""``smdinspect demo``: the whole pipeline on a synthetic board, no hardware."""

from __future__ import annotations

import argparse
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "demo", help="simulate, sweep, reconstruct and inspect a synthetic board",
        description="Sweep a synthetic demo board with injected defects through the "
                    "simulated rig (fake GRBL stage on a pseudo-terminal + simulated camera), "
                    "reconstruct it, inspect every joint and write the reports.")
    p.add_argument("--out", type=Path, default=Path("smdinspect-demo"),
                   help="output folder (default ./smdinspect-demo; replaced on each run)")
    p.add_argument("--seed", type=int, default=7, help="random seed (default 7)")
    p.add_argument("--defects", default=None,
                   help="defects to inject, e.g. R3.1:insufficient,U1.4:bridge "
                        "(default: a few of different classes)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..cli import progress_callback
    from ..demo import demo_board_path, run_demo
    from ..synth import parse_defects

    defects = None
    if args.defects is not None:
        from ..inspect import load_board

        defects = parse_defects(args.defects, board=load_board(demo_board_path()))
    bars = {name: progress_callback(args, label)
            for name, label in (("sweep", "sweep"), ("reconstruct", "focus"))}
    res = run_demo(args.out, seed=args.seed, defects=defects,
                   progress=lambda stage, d, t: bars[stage](d, t))
    result = res.inspection
    truth = {j["id"]: j["class"] for j in res.labels["joints"]}
    joints = result.joints
    found = {j.id: j.verdict.value for j in joints}
    injected = {k: v for k, v in truth.items() if v != "ok"}
    hits = sum(found.get(k) == v for k, v in injected.items())
    # A bridge joins two joints: its partner ("bridged_by") may rightly be called a bridge too.
    partners = {j["id"] for j in res.labels["joints"] if j.get("bridged_by")}
    false_calls = [k for k, v in found.items() if truth.get(k) == "ok" and v not in ("ok", "unreliable")
                   and not (k in partners and v == "bridge")]
    unreliable = [k for k, v in found.items() if v == "unreliable"]
    defective = {k: v for k, v in found.items() if v not in ("ok", "unreliable")}
    print(f"smdinspect demo: board '{result.board}', {len(joints)} joints "
          f"(sweep {res.seconds['sweep']} s, reconstruct + inspect {res.seconds['inspect']} s)")
    print(f"  registration: fitness {result.registration.fitness:.2f}, "
          f"rmse {result.registration.rmse_mm:.3f} mm")
    print(f"  defects found: {len(defective)} "
          + (", ".join(f"{k} {v}" for k, v in sorted(defective.items())) or "none"))
    print(f"  injected: {len(injected)} ({', '.join(f'{k} {v}' for k, v in sorted(injected.items()))}); "
          f"found with the right class: {hits}/{len(injected)}; false calls on good joints: "
          f"{len(false_calls)}" + (f" ({', '.join(false_calls)})" if false_calls else ""))
    if unreliable:
        print(f"  unreliable (not judged): {', '.join(sorted(unreliable))}")
    rd = res.report_dir
    print("  open:")
    for name in ("report.html", "view3d.png", "height.png", "cloud.ply", "mesh.stl", "report.json",
                 "junit.xml"):
        print(f"    {rd / name}")
    return result.exit_code
