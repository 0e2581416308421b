"""``smdinspect batch``: inspect every stack under a folder (process pool or Dask)."""

from __future__ import annotations

import argparse
import logging
import sys
import threading
import time
from pathlib import Path

log = logging.getLogger(__name__)

#: Boards listed by name at the end of a run (errors first); the rest are in the summary.
_MAX_LISTED = 20

_EPILOG = """\
exit codes: 0 every board passed; 1 some board has defects; 2 some board could not be
inspected (bad or corrupt stack, board not located, crash) or bad arguments. An error
outranks defects. Per-board codes are in REPORTS_DIR/summary.csv.

Rerunning skips the boards whose reports are complete and whose inputs (stack.json,
frames, board file, settings) did not change; --force redoes them.

processes and threads: --processes N boards are inspected at once, each in its own
process, and each board uses --threads T threads (default: CPUs / N). (In `smdinspect
reconstruct`, --workers counts threads; here the older name --workers is an alias of
--processes.) On Dask, every Dask worker thread runs one board.

Dask and TLS: --dask-local starts a private cluster on 127.0.0.1 secured with mutual TLS
(a key and certificate generated for this run, so no other user of the machine can
connect to it) and a private scratch folder. For an existing cluster started with TLS,
  dask scheduler --tls-ca-file ca.pem --tls-cert sched.pem --tls-key sched.key
  dask worker tls://HOST:8786 --tls-ca-file ca.pem --tls-cert w.pem --tls-key w.key
give its tls:// address and a client certificate the CA signed:
  smdinspect batch STACKS --board B.json --out R --scheduler tls://HOST:8786 \\
      --tls-ca-file ca.pem --tls-cert client.pem --tls-key client.key
(or set Dask's DASK_DISTRIBUTED__COMM__TLS__CA_FILE, ..._CLIENT__CERT, ..._CLIENT__KEY).
"""


def register(sub: argparse._SubParsersAction) -> None:
    from ..inspect._config import InspectConfig
    from ..sff import OPERATORS
    from .reconstruct import add_calibration_argument, add_cloud_filled_argument

    p = sub.add_parser(
        "batch", help="inspect every stack under a folder (process pool or Dask cluster)",
        description="Inspect every stack directory (a folder holding stack.json) under\n"
                    "STACKS_DIR against one reference board. Each board's reports go to\n"
                    "REPORTS_DIR/<stack path>/; summary.csv, summary.json and one merged\n"
                    "junit.xml go to REPORTS_DIR. Boards run in a local process pool, or on\n"
                    "a Dask cluster with --scheduler / --dask-local.",
        epilog=_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("stacks_dir", type=Path, metavar="STACKS_DIR",
                   help="folder searched recursively for stack directories")
    p.add_argument("--board", required=True, type=Path, metavar="BOARD.json",
                   help="reference board file (e.g. references/demo_board.json)")
    p.add_argument("--out", required=True, type=Path, metavar="REPORTS_DIR",
                   help="batch report folder (created)")
    p.add_argument("--processes", "--workers", dest="processes", type=int, default=None,
                   metavar="N",
                   help="boards inspected at once: worker processes of the local pool "
                        "(default: number of CPUs); --workers is an older name")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--scheduler", metavar="ADDRESS",
                       help="run on an existing Dask cluster, e.g. tcp://HOST:8786 or, with "
                            "the --tls-* files, tls://HOST:8786 (workers need the same "
                            "smdinspect and must see the same paths)")
    where.add_argument("--dask-local", type=int, metavar="N", default=None,
                       help="start a private local Dask cluster of N worker processes for "
                            "this run (TLS with a per-run certificate)")
    t = p.add_argument_group("TLS for --scheduler tls://... (PEM files)")
    t.add_argument("--tls-ca-file", type=Path, metavar="CA.pem", default=None,
                   help="certificate authority of the cluster's certificates")
    t.add_argument("--tls-cert", type=Path, metavar="CERT.pem", default=None,
                   help="this client's certificate (signed by that authority)")
    t.add_argument("--tls-key", type=Path, metavar="KEY.pem", default=None,
                   help="its private key, if not in the --tls-cert file")
    p.add_argument("--force", action="store_true",
                   help="redo every board, even those whose reports are up to date")
    f = p.add_argument_group("inspection options (as for smdinspect inspect)")
    f.add_argument("--operator", default=None, choices=OPERATORS, metavar="OP",
                   help="focus measure (default sml)")
    f.add_argument("--window-px", type=int, default=None,
                   help="focus window side, odd (default: the inspection's, about 70 µm of "
                        "the board and at least 5 px, from the first stack's pixel size)")
    f.add_argument("--fit", default=None, choices=["power", "gauss3", "lsq", "argmax"],
                   help="peak model (default power)")
    f.add_argument("--fit-half-width", type=int, default=None,
                   help="frames kept each side of the peak (default 3)")
    f.add_argument("--min-confidence", type=float, default=None,
                   help="pixels below this confidence are unreliable (default 0.5)")
    f.add_argument("--align", action="store_true", default=None,
                   help="register frames first")
    f.add_argument("--prefilter", default=None, metavar="auto|PX",
                   help="Gaussian σ (px) smoothing each frame before the focus measure, "
                        "against sensor noise; 'auto' picks it per stack (default 0: off)")
    f.add_argument("--threads", type=int, default=None, metavar="T",
                   help="threads per board (default: CPUs / processes; 1 on Dask)")
    f.add_argument("--keep-unreliable", action="store_true",
                   help="keep unreliable points in cloud.ply and the mesh")
    add_cloud_filled_argument(f)
    f.add_argument("--inspect-config", type=Path, default=None, metavar="JSON",
                   help="JSON file of InspectConfig settings (see the README, 'Inspection')")
    f.add_argument("--min-reliable-fraction", type=float, default=None,
                   help="joints with a smaller fraction of reliable pixels are 'unreliable' "
                        f"(default {InspectConfig.min_reliable_fraction})")
    f.add_argument("--no-html", action="store_true", help="skip each board's report.html")
    add_calibration_argument(f, "to every board")
    p.add_argument("--no-spc", action="store_true",
                   help="skip SPC across the boards (REPORTS_DIR/spc/: spc.csv, control "
                        "charts, run rules; see `smdinspect spc`)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import dataclasses

    from ..batch import DaskTLS, run_batch
    from ..errors import InputError
    from ..pipeline import inspection_focus_config
    from .inspect import inspect_config_from
    from .reconstruct import prefilter_value

    if args.processes is not None and (args.scheduler or args.dask_local is not None):
        raise InputError("--processes sizes the local process pool; with --scheduler or "
                         "--dask-local the Dask workers run the boards")
    tls = None
    if args.tls_ca_file or args.tls_cert or args.tls_key:
        if not args.scheduler:
            raise InputError("--tls-ca-file/--tls-cert/--tls-key are for --scheduler "
                             "tls://...; --dask-local makes its own certificate")
        if not (args.tls_ca_file and args.tls_cert):
            raise InputError("a TLS scheduler needs both --tls-ca-file and --tls-cert")
        tls = DaskTLS(ca_file=args.tls_ca_file, cert_file=args.tls_cert,
                      key_file=args.tls_key)
    given = {k: getattr(args, k) for k in ("operator", "window_px", "fit", "fit_half_width",
                                           "min_confidence", "align")
             if getattr(args, k) is not None}
    if args.prefilter is not None:
        given["prefilter_px"] = prefilter_value(args.prefilter)
    pixel = None
    if "window_px" not in given:  # one rig: the first stack's pixel size sets the window
        from ..batch import discover_stacks
        from ..pipeline import stack_pixel_size

        found = discover_stacks(args.stacks_dir) if Path(args.stacks_dir).is_dir() else []
        pixel = stack_pixel_size(found[0][1]) if found else None
    focus = dataclasses.replace(inspection_focus_config(pixel), **given)
    bar = BatchProgress(disable=bool(args.quiet))
    try:
        res = run_batch(args.stacks_dir, args.board, args.out, workers=args.processes,
                        threads=args.threads, scheduler=args.scheduler,
                        dask_workers=args.dask_local, tls=tls, force=args.force,
                        focus_config=focus, inspect_config=inspect_config_from(args),
                        keep_unreliable=args.keep_unreliable,
                        cloud_filled=args.cloud_filled, html=not args.no_html,
                        spc=not args.no_spc, progress=bar.boards, board_progress=bar.board,
                        calibration=args.calibration)
    finally:
        bar.close()
    c = res.counts()
    print(f"{len(res.boards)} boards in {res.seconds:.1f} s on {res.executor}: {c['ok']} ok, "
          f"{c['defects']} with defects, {c['error']} errors"
          + (f" ({c['skipped']} unchanged, skipped)" if c["skipped"] else ""))
    # errors first, then boards with defects; the summary has them all
    bad = sorted((b for b in res.boards if b.status.value != "ok"),
                 key=lambda b: (b.status.value != "error", b.stack))
    for b in bad[:_MAX_LISTED]:
        print(f"  {b.stack}: {b.status.value} (exit {b.exit_code}) {b.reason}")
    if len(bad) > _MAX_LISTED:
        print(f"  ... and {len(bad) - _MAX_LISTED} more (see summary.csv)")
    if res.spc is not None:
        drifting = sorted({s.key for s in res.spc.flagged() if s.scope == "joint"})
        print(f"SPC over {len(res.spc.boards)} boards: {len(drifting)} joint(s) with a run "
              f"rule firing" + (f" ({', '.join(drifting[:8])}"
                                + (", ..." if len(drifting) > 8 else "") + ")" if drifting else ""))
    print(f"summary: {res.summary_csv}  junit: {res.junit}"
          + (f"  page: {res.index_html}" if res.index_html else ""))
    return res.exit_code


class BatchProgress:
    """One bar for the whole batch that moves within each board.

    ``boards(done, total)`` counts finished boards; ``board(stack, stage, done, total)``
    (from any thread) moves a running board, or ends it (stage ``done`` or ``skipped``):
    its frames fill
    :data:`RECONSTRUCT_SHARE` of it, measuring and writing its reports the rest. The bar
    shows the boards done, what each running board is doing, elapsed and remaining time;
    no rate is shown (a first update would make it nonsense), and boards skipped as
    unchanged do not count towards the remaining-time estimate.
    """

    #: Share of a board's time spent reconstructing (the rest: locate, measure, report).
    RECONSTRUCT_SHARE = 0.7
    _MIN_REDRAW_S = 0.2
    #: The status goes in tqdm's ``desc``; no ``{rate}``.
    BAR_FORMAT = "batch {percentage:3.0f}%|{bar}| {desc} [{elapsed}<{remaining}]"

    def __init__(self, *, disable: bool = False, file=None) -> None:
        self.disable = disable
        self.file = file if file is not None else sys.stderr
        self.lock = threading.Lock()
        self.bar = None
        self.total = 0
        self.finished: set[str] = set()
        self.running: dict[str, tuple[str, int, int]] = {}
        self.n_done = 0
        self.n_skip_fast = 0
        self._last_draw = 0.0

    # -- callbacks ------------------------------------------------------------------
    def boards(self, done: int, total: int) -> None:
        with self.lock:
            self.total = total
            self._open()
            self.n_done = done
            self._draw(force=True)

    def board(self, stack: str, stage: str, done: int, total: int) -> None:
        with self.lock:
            if stage in ("done", "skipped"):  # its result came back (before boards())
                self.finished.add(stack)
                was_running = self.running.pop(stack, None) is not None
                if stage == "skipped" and not was_running:
                    self.n_skip_fast += 1
                return
            if stack in self.finished:
                return  # a message that arrived after the board's result
            self.running[stack] = (stage, int(done), int(total))
            self._draw()

    # -- what is drawn --------------------------------------------------------------
    def fraction(self, stage: str, done: int, total: int) -> float:
        if stage == "reconstruct":
            return self.RECONSTRUCT_SHARE * (done / total if total > 0 else 0.0)
        return self.RECONSTRUCT_SHARE

    def position(self) -> float:
        """Boards done plus the fractions of those running."""
        return self.n_done + sum(self.fraction(*v) for v in self.running.values())

    def status(self) -> str:
        parts = [f"{self.n_done}/{self.total} boards done"]
        shown = sorted(self.running.items())[:3]
        for name, (stage, done, total) in shown:
            what = (f"frame {done}/{total}" if stage == "reconstruct"
                    else "measuring + writing reports")
            parts.append(f"{name}: {what}")
        if len(self.running) > len(shown):
            parts.append(f"+{len(self.running) - len(shown)} running")
        if not self.running and self.n_done < self.total:
            parts.append("starting workers")
        return "; ".join(parts)

    def _open(self) -> None:
        if self.disable or self.bar is not None:
            return
        from tqdm import tqdm

        self.bar = tqdm(total=self.total, file=self.file, leave=False, dynamic_ncols=True,
                        disable=None, bar_format=self.BAR_FORMAT)

    def _draw(self, *, force: bool = False) -> None:
        if self.bar is None:
            return
        now = time.monotonic()
        if not force and now - self._last_draw < self._MIN_REDRAW_S:
            return
        self._last_draw = now
        self.bar.total = self.total
        # boards skipped at once would make the remaining time look tiny: leave them
        # out of the rate (tqdm's rate is (n - initial) / elapsed)
        self.bar.initial = self.n_skip_fast
        self.bar.n = min(float(self.total), self.position())
        self.bar.set_description_str(self.status(), refresh=False)
        self.bar.refresh()

    def close(self) -> None:
        with self.lock:
            if self.bar is not None:
                self.bar.close()
                self.bar = None
