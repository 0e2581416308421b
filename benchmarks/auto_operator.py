"""``--operator auto`` against the default SML on the real stacks in ``../shared/data``
(the README's texture-study section quotes it).

For each stack: the texture features and the operator auto picks, then coverage of the
aligned field and outliers against a robust local surface (as ``real_stacks.py``) for
SML and for the pick.

    .venv/bin/python benchmarks/auto_operator.py [--data DIR]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from real_stacks import STACKS, figures, open_real_stack  # noqa: E402

from smdinspect.sff import FocusConfig, reconstruct  # noqa: E402
from smdinspect.stack import FocalStack  # noqa: E402
from smdinspect.study import choose_operator  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    args = ap.parse_args(argv)
    for name, (pattern, step) in STACKS.items():
        if not (args.data / name).is_dir():
            print(f"{name}: not found in {args.data}")
            continue
        stack, _, _ = open_real_stack(args.data / name, pattern, step)
        t0 = time.perf_counter()
        choice = choose_operator(stack)
        t_choice = time.perf_counter() - t0
        print(f"{name}: {choice.features.describe()} -> {choice.operator} ({t_choice:.1f} s)")
        for op in dict.fromkeys(["sml", choice.operator]):
            config = FocusConfig(operator=op, align=True)
            t0 = time.perf_counter()
            full = reconstruct(stack, config)
            seconds = time.perf_counter() - t0
            even = reconstruct(FocalStack(stack.frames[::2], pixel_size_mm=stack.pixel_size_mm),
                               config)
            r = figures(name, full, even, full.field)
            print(f"  {op:5s} coverage {100 * r['coverage']:5.1f} %, outliers "
                  f"{100 * r['outliers']:.2f} %, reconstruct {seconds:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
