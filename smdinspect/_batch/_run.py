"""``run_batch``: inspect every stack under a folder, resumably."""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator

from ..errors import InputError
from ._discover import discover_stacks, file_sha256
from ._job import DEFAULT_INSPECT_FN, BoardJob, BoardResult, BoardStatus, clean_leftovers
from ._report import merge_junit, write_summary_csv, write_summary_json
from ._runners import DaskTLS, dask_client, run_dask, run_local

__all__ = ["BatchResult", "run_batch"]

log = logging.getLogger(__name__)

SUMMARY_CSV = "summary.csv"
SUMMARY_JSON = "summary.json"
JUNIT_XML = "junit.xml"
INDEX_HTML = "index.html"
#: Every board's IPC-CFX message in one list (the name of smdinspect.inspect._cfx.CFX_FILE).
CFX_JSON = "cfx_units_inspected.json"
SPC_DIR = "spc"
LOCK_FILE = ".smdinspect-batch.lock"
#: Focus settings that change speed, not results: left out of the input fingerprint.
_NEUTRAL_FOCUS_KEYS = ("workers",)


@dataclass(frozen=True)
class BatchResult:
    """What :func:`run_batch` did.

    Attributes
    ----------
    boards : tuple of BoardResult
        One per stack, sorted by stack name.
    out_dir : Path
        The batch's report folder.
    executor : str
        Where the boards ran (``"process-pool(2 workers)"``, ``"dask(tcp://...)"``...).
    seconds : float
        Wall time of the whole batch.
    summary_csv, summary_json, junit : Path
        The batch-level outputs.
    index_html : Path or None
        ``index.html``: every board's verdict linked to its report, and the SPC summary.
    spc : smdinspect.inspect.SpcAnalysis or None
        SPC across the inspected boards (written to ``spc/``), when there were at least
        two and ``spc`` was on.
    """

    boards: tuple[BoardResult, ...]
    out_dir: Path
    executor: str
    seconds: float
    summary_csv: Path
    summary_json: Path
    junit: Path
    #: The batch page (every board's verdict, the SPC summary); None if not written.
    index_html: Path | None = None
    #: SPC across the inspected boards (``spc/spc.csv``, charts); None when not computed.
    spc: Any = None

    @property
    def exit_code(self) -> int:
        """2 if any board errored, else 1 if any board has defects, else 0.

        An error outranks defects: a batch with a board that could not be inspected
        is incomplete, which a CI job must not mistake for "found defects".
        """
        return batch_exit_code(self.boards)

    def counts(self) -> dict[str, int]:
        """Boards per status, plus ``skipped`` (boards whose earlier reports were kept)."""
        out = {s.value: 0 for s in BoardStatus}
        for b in self.boards:
            out[b.status.value] += 1
        out["skipped"] = sum(b.skipped for b in self.boards)
        return out

    @property
    def boards_per_minute(self) -> float:
        """Boards inspected (not skipped) per minute of wall time."""
        run = sum(not b.skipped for b in self.boards)
        return 60.0 * run / self.seconds if self.seconds > 0 else math.nan

    def board(self, stack: str) -> BoardResult:
        for b in self.boards:
            if b.stack == stack:
                return b
        raise KeyError(stack)


def batch_exit_code(boards: Any) -> int:
    """2 if any board errored, else 1 if any has defects, else 0."""
    statuses = {b.status for b in boards}
    if BoardStatus.ERROR in statuses:
        return 2
    if BoardStatus.DEFECTS in statuses:
        return 1
    return 0


@contextlib.contextmanager
def _locked(out_dir: Path) -> Iterator[None]:
    """Hold an exclusive lock on ``out_dir`` (released by the OS if we are killed)."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX: no lock
        yield
        return
    fh = open(out_dir / LOCK_FILE, "a+")
    try:
        try:
            fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise InputError(f"another smdinspect batch is writing into {out_dir}; wait for it "
                             "or choose another --out") from None
        yield
    finally:
        fh.close()


def _is_within(path: Path, parent: Path) -> bool:
    try:
        path.relative_to(parent)
        return True
    except ValueError:
        return False


def run_batch(
    stacks_dir: str | os.PathLike,
    board: str | os.PathLike,
    out_dir: str | os.PathLike,
    *,
    workers: int | None = None,
    threads: int | None = None,
    scheduler: str | None = None,
    dask_workers: int | None = None,
    tls: DaskTLS | None = None,
    force: bool = False,
    focus_config: Any = None,
    inspect_config: Any = None,
    keep_unreliable: bool = False,
    cloud_filled: bool = False,
    html: bool = True,
    spc: bool = True,
    progress: Callable[[int, int], None] | None = None,
    board_progress: Callable[[str, str, int, int], None] | None = None,
    inspect_fn: str = DEFAULT_INSPECT_FN,
    calibration: str | os.PathLike | None = None,
) -> BatchResult:
    """Inspect every stack under ``stacks_dir`` against one reference board.

    Each stack directory (a folder holding ``stack.json``, found recursively; see
    :func:`discover_stacks`) is one board. Its reports (those of
    :func:`smdinspect.pipeline.inspect_stack`) go to ``out_dir / <stack path relative
    to stacks_dir>/``; the batch adds ``summary.csv``, ``summary.json``, one merged
    ``junit.xml`` and ``cfx_units_inspected.json`` (every board's IPC-CFX message, a
    JSON list of envelopes) in ``out_dir``.

    A board that fails (corrupt stack, board not located, a crash) is recorded as
    ``error`` with its reason and never stops the batch. The run is resumable: a board
    whose report folder holds a done-marker for the same input fingerprint (stack.json,
    frame files, board file, settings) and intact outputs is skipped, unless ``force``.
    Board folders appear atomically (written into a temporary sibling, renamed into
    place), so a killed run leaves no half-written report; its temporary folders are
    removed by the next run.

    Parameters
    ----------
    stacks_dir : path
        Folder searched recursively for stack directories.
    board : path
        Reference board file (JSON; see ``references/README.md``). Checked before any
        board runs: a bad board file fails the batch (InputError).
    out_dir : path
        The batch's report folder (created). May lie inside ``stacks_dir`` (it is not
        searched) but not contain it.
    workers : int, optional
        Number of worker *processes* of the local pool, i.e. boards inspected at once
        (default ``os.cpu_count()``, at most one per board); the CLI's ``--processes``.
        Only for the local pool; each process uses ``threads`` threads.
    threads : int, optional
        Threads per board (focus measure, OpenCV, Open3D; replaces
        ``focus_config.workers``). Default: the worker's share of the CPUs,
        ``max(1, cpu_count // pool size)`` in the local pool, 1 on Dask.
    scheduler : str, optional
        Run on an existing Dask distributed cluster at this address
        (``tcp://HOST:8786``, or ``tls://HOST:8786`` with ``tls``); its workers must
        import the same smdinspect and see the same paths.
    dask_workers : int, optional
        Run on a Dask ``LocalCluster`` of this many single-threaded worker processes
        started for this batch: 127.0.0.1, mutual TLS with a certificate generated for
        the run, a private scratch folder, no dashboard.
    tls : DaskTLS, optional
        CA, certificate and key files for a ``tls://`` ``scheduler``.
    force : bool
        Redo every board, even those whose reports are up to date.
    focus_config : smdinspect.sff.FocusConfig, optional
        Defaults to the inspection's own default
        (:func:`smdinspect.pipeline.inspection_focus_config`); its ``workers`` is set
        to ``threads``.
    inspect_config : smdinspect.inspect.InspectConfig, optional
        Defaults to ``InspectConfig()``.
    keep_unreliable : bool
        Passed to the pipeline (unreliable points kept in cloud and mesh).
    cloud_filled : bool
        Passed to the pipeline (``cloud.ply`` also holds the filled points); not with
        ``keep_unreliable``.
    html : bool
        Write each board's ``report.html`` (``False`` is passed on as ``html=False``).
    spc : bool
        After the boards, compute SPC across the inspected ones (at least two) into
        ``out_dir/spc/`` (see :func:`smdinspect.inspect.analyse_reports`; boards in
        stack-name order), and write ``out_dir/index.html`` with every board's verdict
        either way. SPC flags do not change the exit code.
    progress : callable(done, total), optional
        Called with the number of boards finished (skipped ones included).
    board_progress : callable(stack, stage, done, total), optional
        Called as each running board moves: ``("reconstruct", frame, n_frames)``, then
        ``("inspect", 0, 1)`` while it is measured and reported (see
        :data:`smdinspect._batch._job.STAGES`), possibly from another thread; and, from
        this thread when its result is in (just before ``progress``), ``("done", 1, 1)``
        or ``("skipped", 1, 1)``. A late stage call may follow ``done``: ignore it.
    inspect_fn : str
        ``"module:function"`` run per board, with the signature and contract of
        :func:`smdinspect.pipeline.inspect_stack` (the default); it must be importable
        by the workers.
    calibration : path, optional
        Rig calibration file (``smdinspect calibrate``) applied to every board (focal
        plane, z scale); the workers must see it. Its content is part of each board's
        input fingerprint: a new calibration re-inspects every board.

    Returns
    -------
    BatchResult
        ``exit_code`` is 2 if any board errored, else 1 if any has defects, else 0.

    Raises
    ------
    InputError
        Bad arguments, no stack found, a bad board file, ``out_dir`` locked by another
        batch, a Dask scheduler that cannot be reached or whose workers lack smdinspect.
    """
    from .. import __version__
    from ..inspect import InspectConfig, load_board
    from ..pipeline import inspection_focus_config, stack_pixel_size

    t0 = time.perf_counter()
    from ..sff._export import check_cloud_options

    check_cloud_options(keep_unreliable, cloud_filled)
    if scheduler is not None and dask_workers is not None:
        raise InputError("give either scheduler (an existing Dask cluster) or dask_workers "
                         "(a local one), not both")
    if workers is not None and (scheduler is not None or dask_workers is not None):
        raise InputError("workers sizes the local process pool; with a Dask cluster its "
                         "workers run the boards")
    for name, value in (("workers", workers), ("dask_workers", dask_workers),
                        ("threads", threads)):
        if value is not None and (isinstance(value, bool) or not isinstance(value, int)
                                  or value < 1):
            raise InputError(f"{name} must be an integer >= 1; got {value!r}")
    if scheduler is not None and (not isinstance(scheduler, str) or not scheduler.strip()):
        raise InputError(f"scheduler must be an address such as tcp://HOST:8786; got {scheduler!r}")
    if tls is not None and (scheduler is None or not isinstance(tls, DaskTLS)):
        raise InputError("tls (a DaskTLS of certificate files) is for an existing TLS "
                         "scheduler; a local Dask cluster makes its own certificate")

    stacks_dir = Path(stacks_dir)
    out_dir = Path(out_dir)
    if not stacks_dir.is_dir():
        raise InputError(f"stacks folder not found: {stacks_dir}")
    s_real, o_real = stacks_dir.resolve(), out_dir.resolve()
    if _is_within(s_real, o_real):
        raise InputError(f"the report folder {out_dir} must not be (or contain) the stacks "
                         f"folder {stacks_dir}")
    stacks = discover_stacks(stacks_dir, exclude=(out_dir,))
    if not stacks:
        raise InputError(f"no stack directories (folders holding stack.json) under {stacks_dir}")
    for name, path in stacks:
        if _is_within(o_real, path.resolve()):
            raise InputError(f"the report folder {out_dir} lies inside the stack {path}")
        if name in (SUMMARY_CSV, SUMMARY_JSON, JUNIT_XML, INDEX_HTML, CFX_JSON) \
                or name.split("/", 1)[0] == SPC_DIR:
            raise InputError(f"stack folder name {name!r} clashes with a batch output file")

    board_obj = load_board(board)
    board_sha256 = file_sha256(board)
    on_dask = scheduler is not None or dask_workers is not None
    # No more pool processes than boards; the CPUs are shared among those that run.
    pool_size = min(workers or (os.cpu_count() or 1), len(stacks))
    # Each worker's share of the CPUs: Dask workers run one board per thread
    # (LocalCluster: one thread per worker), the local pool splits the CPUs.
    if threads is None:
        threads = 1 if on_dask else max(1, (os.cpu_count() or 1) // pool_size)
    if focus_config is None:  # one rig: the first stack's pixel size sets the window
        focus_config = inspection_focus_config(stack_pixel_size(stacks[0][1]))
    focus_config = dataclasses.replace(focus_config, workers=threads)
    if inspect_config is None:
        inspect_config = InspectConfig()
    focus_key = {k: v for k, v in focus_config.to_dict().items() if k not in _NEUTRAL_FOCUS_KEYS}
    if not isinstance(inspect_fn, str) or ":" not in inspect_fn:
        raise InputError(f"inspect_fn must be 'module:function'; got {inspect_fn!r}")
    settings = {"smdinspect": __version__, "pipeline": inspect_fn, "focus": focus_key,
                "inspect": inspect_config.to_dict(), "keep_unreliable": bool(keep_unreliable),
                "html": bool(html)}
    if cloud_filled:  # only when set: earlier batches' fingerprints stay valid
        settings["cloud_filled"] = True
    if calibration is not None:
        from ..calibrate import read_calibration

        read_calibration(calibration)  # a bad file fails the batch before any board runs
        calibration = str(Path(calibration).resolve())
        # a new calibration re-inspects every board (its content is in the fingerprint)
        settings["calibration_sha256"] = file_sha256(calibration)

    with contextlib.ExitStack() as stack:
        client = None
        if on_dask:  # connect first: an unreachable scheduler leaves nothing behind
            client, executor = stack.enter_context(
                dask_client(scheduler=scheduler, local_workers=dask_workers, tls=tls))
        else:
            executor = f"process-pool({pool_size} workers)"
        out_dir.mkdir(parents=True, exist_ok=True)
        stack.enter_context(_locked(out_dir))
        removed = clean_leftovers(out_dir)
        if removed:
            log.info("removed %d temporary folder(s) left by an interrupted batch", len(removed))
        jobs = [
            BoardJob(name=name, stack_dir=str(path.resolve()), out_dir=str(o_real / name),
                     board=board_obj, board_sha256=board_sha256, settings=settings,
                     focus_config=focus_config, inspect_config=inspect_config,
                     keep_unreliable=bool(keep_unreliable),
                     cloud_filled=bool(cloud_filled), force=bool(force),
                     inspect_fn=inspect_fn, html=bool(html), calibration=calibration or "")
            for name, path in stacks
        ]
        results: dict[str, BoardResult] = {}
        total = len(jobs)

        def on_result(res: BoardResult) -> None:
            results[res.stack] = res
            log.debug("%s: %s (exit %d)%s in %.1f s %s", res.stack, res.status.value,
                      res.exit_code, " skipped, unchanged," if res.skipped else "",
                      res.seconds, res.reason)
            if board_progress is not None:
                board_progress(res.stack, "skipped" if res.skipped else "done", 1, 1)
            if progress is not None:
                progress(len(results), total)

        if progress is not None:
            progress(0, total)
        if client is not None:
            run_dask(jobs, client=client, on_result=on_result, on_progress=board_progress)
        else:
            run_local(jobs, workers=pool_size, on_result=on_result, threads=threads,
                      on_progress=board_progress)

        clean_leftovers(out_dir)  # folders of crashed workers
        boards = tuple(results[j.name] if j.name in results else _lost(j) for j in jobs)
        seconds = time.perf_counter() - t0
        result = BatchResult(boards=boards, out_dir=out_dir, executor=executor,
                             seconds=seconds, summary_csv=out_dir / SUMMARY_CSV,
                             summary_json=out_dir / SUMMARY_JSON, junit=out_dir / JUNIT_XML)
        header = {
            "format": "smdinspect-batch-summary",
            "version": 1,
            "smdinspect": __version__,
            "stacks_dir": str(s_real),
            "board_file": str(Path(board).resolve()),
            "board_sha256": board_sha256,
            "reports_dir": str(o_real),
            "executor": executor,
            "settings": settings,
            "exit_code": result.exit_code,
            "boards_total": total,
            "counts": result.counts(),
            "seconds": round(seconds, 3),
            "boards_per_minute": (None if math.isnan(result.boards_per_minute)
                                  else round(result.boards_per_minute, 3)),
        }
        merge_junit(result.junit, boards)
        write_summary_csv(result.summary_csv, boards)
        write_summary_json(result.summary_json, boards, header)
        _collect_cfx(result)
        result = _batch_pages(result, spc=spc)
    return result


def _collect_cfx(result: BatchResult) -> None:
    """Every board's IPC-CFX UnitsInspected message (not-located boards' too) in one
    list, ``out_dir/cfx_units_inspected.json``; a problem here is logged, never fails
    the batch."""
    from ..inspect._cfx import CFX_FILE, collect_units_inspected

    try:
        collect_units_inspected([b.out_dir for b in result.boards
                                 if (Path(b.out_dir) / CFX_FILE).is_file()],
                                result.out_dir / CFX_JSON)
    except OSError as exc:
        log.warning("cannot write %s: %s", result.out_dir / CFX_JSON, exc)


def _batch_pages(result: BatchResult, *, spc: bool) -> BatchResult:
    """SPC across the inspected boards (``spc/``) and ``index.html``; a problem here is
    logged, never fails the batch."""
    from ..inspect._spc_report import analyse_reports, write_batch_page, write_spc

    analysis, note = None, ""
    inspected = [b for b in result.boards if b.status is not BoardStatus.ERROR]
    if spc and len(inspected) >= 2:
        try:
            analysis = analyse_reports([b.out_dir for b in inspected],
                                       labels=[b.stack for b in inspected], order="name")
            write_spc(analysis, result.out_dir / SPC_DIR)
        except (InputError, OSError, ValueError) as exc:
            log.warning("SPC across the boards not computed: %s", exc)
            analysis, note = None, f"not computed: {exc}"
    elif spc:
        note = "needs at least 2 inspected boards"
    try:
        page = write_batch_page(result.out_dir / INDEX_HTML, [b.to_row() for b in result.boards],
                                title=f"smdinspect batch: {len(result.boards)} boards",
                                spc=analysis, spc_dir=SPC_DIR, note=note)
    except OSError as exc:
        log.warning("cannot write %s: %s", result.out_dir / INDEX_HTML, exc)
        page = None
    return dataclasses.replace(result, index_html=page, spc=analysis)


def _lost(job: BoardJob) -> BoardResult:  # pragma: no cover - executors report every job
    return BoardResult(stack=job.name, status=BoardStatus.ERROR, exit_code=2, joints=None,
                       defects=None, unreliable=None, reason="no result came back",
                       seconds=0.0, skipped=False, out_dir=job.out_dir)
