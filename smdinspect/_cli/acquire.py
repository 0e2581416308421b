"""``smdinspect acquire --rig RIG.toml --out DIR [--resume]``: sweep a rig, write a stack."""

from __future__ import annotations

import argparse
import logging

log = logging.getLogger(__name__)


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "acquire",
        help="drive a motion stage and camera through a focal sweep and write a stack",
        description=(
            "Move the stage through the rig file's sweep, capture a frame at every step "
            "and write a focal stack (stack.json + frames) recording the z each frame was "
            "actually taken at. Ctrl-C stops the stage (feed hold) and keeps the frames; "
            "--resume continues an interrupted sweep. Try it without hardware: "
            "--rig examples/sim_rig.toml."
        ),
    )
    p.add_argument("--rig", required=True, metavar="RIG.toml",
                   help="rig file: [stage], [mapping], [camera], [optics], [sweep]")
    p.add_argument("--out", required=True, metavar="DIR", help="stack directory to write")
    p.add_argument("--resume", action="store_true",
                   help="continue the interrupted sweep in DIR (the rig file must be unchanged)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..acquire import acquire, load_rig
    from ..cli import progress_callback

    rig = load_rig(args.rig)
    progress = progress_callback(args, "acquire")
    try:
        result = acquire(rig, args.out, resume=args.resume, progress=progress)
    finally:
        progress.close()
    z = result.z_mm
    if not getattr(args, "quiet", False):
        print(f"{result.root}: {result.n_frames} frames ({result.n_new} new), z_mm "
              f"{z.min():.4f} .. {z.max():.4f}, in {result.elapsed_s:.1f} s")
    return 0
