"""Command line: ``smdinspect demo | simulate | acquire | reconstruct | inspect | batch``.

Parses arguments, sets up logging and progress bars, calls the library, and turns
:class:`~smdinspect.errors.SmdInspectError` into a one-line message and an exit code:

====  ==========================================================
0     success (all joints pass)
1     inspection found defects
2     bad input (arguments, files, board file), or an output that cannot be written
      (no space left on device, no permission)
3     the board could not be located in the measurement
4     hardware failure (stage, camera)
70    internal error: an unexpected exception, i.e. a bug in smdinspect (one line;
      the traceback with -v); never read as "inspected"
130   interrupted (Ctrl-C); work finished so far is kept
====  ==========================================================

``-v`` and ``-q`` work before or after the subcommand.
"""

from __future__ import annotations

import argparse
import errno
import importlib
import logging
import sys
from typing import Callable, Sequence

from . import __version__
from .errors import SmdInspectError

log = logging.getLogger(__name__)

#: Exit code of an unexpected exception (a bug); BSD sysexits' EX_SOFTWARE.
EXIT_INTERNAL = 70

# One module per subcommand in smdinspect/_cli/, each with register(subparsers),
# which adds its parser and sets ``func`` to a callable(args) -> int.
COMMANDS = ("demo", "simulate", "acquire", "reconstruct", "inspect", "batch", "board", "calibrate", "grr", "spc", "study")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="smdinspect",
        description="Shape-from-focus 3D inspection of SMD solder joints.",
    )
    parser.add_argument("--version", action="version", version=f"smdinspect {__version__}")
    _add_verbosity(parser, "")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        try:
            module = importlib.import_module(f"smdinspect._cli.{name}")
        except ModuleNotFoundError as exc:
            if exc.name != f"smdinspect._cli.{name}":
                raise
            continue
        module.register(sub)
    for subparser in sub.choices.values():
        _add_verbosity(subparser, "sub_")  # -v / -q after the subcommand too
    return parser


def _add_verbosity(parser: argparse.ArgumentParser, prefix: str) -> None:
    parser.add_argument("-v", "--verbose", action="count", default=0, dest=f"{prefix}verbose",
                        help="more log output; -v also shows tracebacks on errors")
    parser.add_argument("-q", "--quiet", action="store_true", dest=f"{prefix}quiet",
                        help="only warnings and errors; no progress bars")


def progress_callback(args: argparse.Namespace, desc: str, unit: str = "frame") -> "Progress":
    """A ``progress(done, total)`` callback drawing a tqdm bar on stderr (unless quiet)."""
    return Progress(desc, unit=unit, disable=bool(getattr(args, "quiet", False)))


class Progress:
    """Adapter from the library's ``progress(done, total)`` callbacks to a tqdm bar."""

    def __init__(self, desc: str, *, unit: str = "frame", disable: bool = False) -> None:
        self.desc, self.unit, self.disable = desc, unit, disable
        self.bar = None

    def __call__(self, done: int, total: int) -> None:
        if self.disable:
            return
        if self.bar is None:
            from tqdm import tqdm

            # initial=done: work finished before the first call does not count as a burst
            # of speed (the first update showed "21399 frame/s")
            self.bar = tqdm(total=total, initial=done, desc=self.desc, unit=self.unit,
                            file=sys.stderr, leave=False, dynamic_ncols=True, disable=None)
        self.bar.total = total
        self.bar.update(done - self.bar.n)
        if done >= total:
            self.close()

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    args.verbose += getattr(args, "sub_verbose", 0)
    args.quiet = args.quiet or getattr(args, "sub_quiet", False)
    level = logging.WARNING if args.quiet else (logging.DEBUG if args.verbose > 1 else logging.INFO)
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s", force=True)
    for noisy in ("distributed", "asyncio", "matplotlib", "PIL", "trimesh"):
        logging.getLogger(noisy).setLevel(max(level, logging.WARNING))
    func: Callable[[argparse.Namespace], int] | None = getattr(args, "func", None)
    if func is None:
        parser.print_help()
        return 2
    try:
        return int(func(args))
    except SmdInspectError as exc:
        return _fail(args, str(exc), exc.exit_code)
    except KeyboardInterrupt:
        print(f"smdinspect {args.command}: interrupted; finished work was kept", file=sys.stderr)
        return 130
    except OSError as exc:
        if exc.errno in (errno.ENOSPC, errno.EDQUOT):
            return _fail(args, f"no space left on device: {exc.filename or exc}", 2)
        return _fail(args, str(exc), 2)
    except MemoryError:
        return _fail(args, "out of memory (an input far larger than expected?); "
                           "rerun with -v for the traceback", EXIT_INTERNAL, "internal error")
    except Exception as exc:  # noqa: BLE001 - a bug: one line and its own exit code
        return _fail(args, f"{type(exc).__name__}: {exc}"[:300] + "; this is a bug in smdinspect "
                     "(rerun with -v for the traceback)", EXIT_INTERNAL, "internal error")


def _fail(args: argparse.Namespace, message: str, code: int, kind: str = "error") -> int:
    """Print the one-line message (and with -v the traceback) and return ``code``."""
    if args.verbose:
        log.exception("failed")
    text = " ".join(message.split())  # one line, whatever the exception held
    print(f"smdinspect {args.command}: {kind}: {text}", file=sys.stderr)
    return code


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
