"""One board of a batch: the job that runs in a worker process, its result, the
done-marker that makes a batch resumable, and the atomic install of its report folder.

Everything here is importable by a worker (a process-pool child or a Dask worker) and
picklable: :func:`run_board` is a plain module-level function of one :class:`BoardJob`.
"""

from __future__ import annotations

import importlib
import json
import logging
import math
import os
import shutil
import tempfile
import time
import traceback
from dataclasses import dataclass, field, replace
from datetime import datetime, timezone
from enum import Enum
from pathlib import Path
from typing import Any, Callable

from .. import _atomic
from ..errors import SmdInspectError
from ._discover import file_sha256, stack_input_sha256

__all__ = [
    "DONE_MARKER",
    "ERROR_FILE",
    "STAGES",
    "BoardJob",
    "BoardResult",
    "BoardStatus",
    "clean_leftovers",
    "read_done_marker",
    "record_error",
    "run_board",
    "set_progress_sink",
]

log = logging.getLogger(__name__)

#: Written last into a board's report folder; its presence (with a matching input
#: fingerprint and intact outputs) is what "this board is done" means.
DONE_MARKER = "batch-done.json"
#: Written into the report folder of a board that failed (no done-marker then).
ERROR_FILE = "error.json"
MARKER_FORMAT = "smdinspect-batch-done"
MARKER_VERSION = 1
#: Prefixes of the temporary sibling folders; only folders named like this are ever
#: removed by the clean-up of a later run.
PARTIAL_PREFIX = ".smdinspect-partial-"
OLD_PREFIX = ".smdinspect-old-"
DEFAULT_INSPECT_FN = "smdinspect.pipeline:inspect_stack"
_UMASK = os.umask(0)
os.umask(_UMASK)

#: Stages a running board reports, in order: ``("reconstruct", frame, n_frames)`` per
#: frame (at most a few per second), then ``("inspect", 0, 1)`` while it is located,
#: measured and its reports written. Its result ends it.
STAGES = ("reconstruct", "inspect")
#: Minimum seconds between two ``reconstruct`` messages of one board.
_PROGRESS_EVERY_S = 0.2

#: Where :func:`run_board` sends its progress in this process: installed by the local
#: pool's initializer (a queue's ``put_nowait``); Dask workers use the job's topic.
_progress_sink: Callable[[tuple[str, str, int, int]], None] | None = None


def set_progress_sink(sink: Callable[[tuple[str, str, int, int]], None] | None) -> None:
    """Send the progress of the boards run in this process to ``sink(message)``."""
    global _progress_sink
    _progress_sink = sink


class BoardStatus(str, Enum):
    """Outcome of one board."""

    #: Inspected; no joint has a defect.
    OK = "ok"
    #: Inspected; at least one joint has a defect.
    DEFECTS = "defects"
    #: Not inspected: bad or corrupt stack, board not located, worker crash...
    ERROR = "error"


@dataclass(frozen=True)
class BoardJob:
    """Everything a worker needs to inspect one board (picklable).

    Paths are absolute strings so that workers started elsewhere (Dask) resolve them
    the same way; they must see the same file system.
    """

    name: str
    stack_dir: str
    out_dir: str
    board: Any  # smdinspect.inspect.Board
    board_sha256: str
    settings: dict[str, Any]
    focus_config: Any = None  # smdinspect.sff.FocusConfig
    inspect_config: Any = None  # smdinspect.inspect.InspectConfig
    keep_unreliable: bool = False
    #: ``True``: cloud.ply also holds the filled points (passed on as ``cloud_filled``)
    cloud_filled: bool = False
    force: bool = False
    #: ``"module:function"`` with the signature of
    #: :func:`smdinspect.pipeline.inspect_stack`, imported in the worker.
    inspect_fn: str = DEFAULT_INSPECT_FN
    #: ``False``: no report.html (passed on as ``html=False``).
    html: bool = True
    #: Dask event topic the worker sends the board's progress to (empty: none).
    progress_topic: str = ""
    #: Rig calibration file (absolute path; empty: none), passed on as ``calibration``.
    calibration: str = ""

    @property
    def threads(self) -> int:
        """Threads OpenCV and Open3D may use in the worker: as many as the focus
        measure's (the worker's share of the CPUs)."""
        return int(getattr(self.focus_config, "workers", 1))


@dataclass(frozen=True)
class BoardResult:
    """One row of the batch summary.

    Attributes
    ----------
    stack : str
        The stack's path relative to the stacks folder (= its report folder).
    status : BoardStatus
    exit_code : int
        What ``smdinspect inspect`` would have returned for this board: 0 ok,
        1 defects, 2 bad input (or a crash), 3 board not located.
    joints, defects, unreliable : int or None
        Joint counts (``None`` when the board errored).
    reason : str
        Why it errored, or the defective joints; empty when ok.
    seconds : float
        Wall time of the board's inspection (for a skipped board: of the run that
        made its reports).
    skipped : bool
        The reports of an earlier run were kept (inputs unchanged).
    out_dir : str
        The board's report folder.
    input_sha256 : str
        Fingerprint of the inputs (see :func:`stack_input_sha256`); empty if unknown.
    """

    stack: str
    status: BoardStatus
    exit_code: int
    joints: int | None
    defects: int | None
    unreliable: int | None
    reason: str
    seconds: float
    skipped: bool
    out_dir: str
    input_sha256: str = ""
    detail: str = field(default="", repr=False, compare=False)

    def to_row(self) -> dict[str, Any]:
        """The summary row (JSON types)."""
        return {
            "stack": self.stack,
            "status": self.status.value,
            "exit_code": self.exit_code,
            "joints": self.joints,
            "defects": self.defects,
            "unreliable": self.unreliable,
            "reason": self.reason,
            "seconds": round(self.seconds, 3),
            "skipped": self.skipped,
            "report_dir": self.out_dir,
        }


def run_board(job: BoardJob) -> BoardResult:
    """Inspect one board; never raises for a problem of the board itself.

    Skips the board when its report folder holds a valid done-marker for the same
    input fingerprint (unless ``job.force``). Otherwise runs
    :func:`smdinspect.pipeline.inspect_stack` into a temporary sibling folder, writes
    the done-marker last, and renames the folder into place, so the report folder is
    either the complete old one or the complete new one. A board that fails gets a
    folder with ``error.json`` (next to whatever the pipeline wrote before failing,
    e.g. the reconstruction and a ``not_located`` report.json) and no done-marker.
    """
    t0 = time.perf_counter()
    out_dir = Path(job.out_dir)
    try:
        digest = stack_input_sha256(job.stack_dir, board_sha256=job.board_sha256,
                                    settings=job.settings)
    except OSError as exc:
        result = _error(job, t0, 2, f"cannot read {Path(job.stack_dir) / 'stack.json'}: "
                                    f"{exc.strerror or exc}", digest="")
        record_error(job, result)
        return result
    if not job.force:
        done = read_done_marker(out_dir, input_sha256=digest)
        if done is not None:
            return replace(done, stack=job.name, out_dir=job.out_dir, skipped=True)

    try:
        out_dir.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f"{PARTIAL_PREFIX}{out_dir.name}-",
                                    dir=out_dir.parent))
        os.chmod(tmp, 0o777 & ~_UMASK)
    except OSError as exc:
        return _error(job, t0, 2, f"cannot create the report folder {out_dir}: "
                                  f"{exc.strerror or exc}", digest=digest)
    try:
        limit_native_threads(job.threads)
        result = _inspect_into(job, tmp, t0, digest, _reporter(job))
        try:
            if result.status is BoardStatus.ERROR:
                _write_error(tmp, job, result)
            else:
                _write_marker(tmp, result)
            _install(tmp, out_dir)
        except OSError as exc:
            return _error(job, t0, 2, f"cannot write the reports into {out_dir}: "
                                      f"{exc.strerror or exc}", digest=digest)
        return result
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


def limit_native_threads(threads: int) -> None:
    """Let OpenCV and Open3D use at most ``threads`` threads in this process.

    A worker's share of the CPUs: without it every worker starts one thread per CPU
    (oversubscription).
    """
    try:
        import cv2

        cv2.setNumThreads(int(threads))
    except ImportError:  # pragma: no cover - a dependency
        pass
    try:
        import open3d

        open3d.utility.set_max_threads(int(threads))
    except (ImportError, AttributeError):  # pragma: no cover - older Open3D
        pass


def _reporter(job: BoardJob) -> Callable[[str, int, int], None] | None:
    """``report(stage, done, total)`` for this board, or ``None`` when nobody listens.

    Never raises (progress is best effort) and throttles the per-frame messages.
    """
    send: Callable[[tuple[str, str, int, int]], None] | None = _progress_sink
    if job.progress_topic:
        try:
            from distributed import get_worker

            worker = get_worker()
        except (ImportError, ValueError):
            worker = None
        if worker is not None:
            topic = job.progress_topic

            def send(msg: tuple[str, str, int, int]) -> None:
                worker.log_event(topic, list(msg))
    if send is None:
        return None
    last = [-math.inf]

    def report(stage: str, done: int, total: int) -> None:
        now = time.monotonic()
        if stage == "reconstruct" and 0 < done < total and now - last[0] < _PROGRESS_EVERY_S:
            return
        last[0] = now
        try:
            send((job.name, stage, int(done), int(total)))
        except Exception:  # a full or closed queue, a closing worker: not the board's fault
            pass

    return report


def _inspect_into(job: BoardJob, tmp: Path, t0: float, digest: str,
                  report: Callable[[str, int, int], None] | None = None) -> BoardResult:
    """Run the pipeline into ``tmp``; the result (status error on any failure)."""
    try:
        from ..stack import FocalStack

        inspect_stack = _resolve(job.inspect_fn)
        stack = FocalStack.open(job.stack_dir)
        extra: dict[str, Any] = {} if job.html else {"html": False}
        if job.calibration:
            extra["calibration"] = job.calibration
        if job.cloud_filled:
            extra["cloud_filled"] = True
        if report is not None:
            n_frames = len(stack)
            report("reconstruct", 0, n_frames)

            def frames(done: int, total: int) -> None:
                report("reconstruct", done, total)
                if done >= total:
                    report("inspect", 0, 1)

            extra["progress"] = frames
        res = inspect_stack(stack, job.board, tmp, focus_config=job.focus_config,
                            inspect_config=job.inspect_config,
                            keep_unreliable=job.keep_unreliable, **extra)
    except SmdInspectError as exc:
        return _error(job, t0, exc.exit_code, str(exc), digest=digest)
    except MemoryError:
        return _error(job, t0, 2, "out of memory while inspecting this board", digest=digest)
    except Exception as exc:  # a bug or an unexpected library error: this board only
        log.debug("board %s crashed", job.name, exc_info=True)
        return _error(job, t0, 2, f"internal error: {type(exc).__name__}: {exc}",
                      digest=digest, detail=traceback.format_exc())
    defects = list(res.defects)
    if defects:
        shown = ", ".join(f"{j.id} {j.verdict.value}" for j in defects[:6])
        more = f", +{len(defects) - 6} more" if len(defects) > 6 else ""
        reason = f"{len(defects)} defective joint{'s' if len(defects) > 1 else ''}: {shown}{more}"
    else:
        reason = ""
    return BoardResult(
        stack=job.name,
        status=BoardStatus.DEFECTS if res.exit_code else BoardStatus.OK,
        exit_code=int(res.exit_code),
        joints=len(res.joints),
        defects=len(defects),
        unreliable=len(res.unreliable),
        reason=reason,
        seconds=time.perf_counter() - t0,
        skipped=False,
        out_dir=job.out_dir,
        input_sha256=digest,
    )


def _resolve(spec: str) -> Callable[..., Any]:
    module, _, name = spec.partition(":")
    return getattr(importlib.import_module(module), name)


def _error(job: BoardJob, t0: float, exit_code: int, reason: str, *, digest: str,
           detail: str = "") -> BoardResult:
    reason = " ".join(str(reason).split()) or "unknown error"
    return BoardResult(stack=job.name, status=BoardStatus.ERROR, exit_code=int(exit_code),
                       joints=None, defects=None, unreliable=None, reason=reason,
                       seconds=time.perf_counter() - t0, skipped=False, out_dir=job.out_dir,
                       input_sha256=digest, detail=detail)


def _utc_now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


def _write_marker(folder: Path, result: BoardResult) -> None:
    """Hash every output file, then write the done-marker (atomically, last)."""
    from .. import __version__

    outputs = {}
    for p in sorted(folder.rglob("*")):
        if p.is_file() and p.name != DONE_MARKER:
            outputs[p.relative_to(folder).as_posix()] = file_sha256(p)
    doc = {
        "format": MARKER_FORMAT,
        "version": MARKER_VERSION,
        "smdinspect": __version__,
        "finished_utc": _utc_now(),
        **{k: v for k, v in result.to_row().items() if k not in ("skipped", "report_dir")},
        "seconds": result.seconds,
        "input_sha256": result.input_sha256,
        "outputs": outputs,
    }
    _atomic.write_json(folder / DONE_MARKER, doc)


def _write_error(folder: Path, job: BoardJob, result: BoardResult) -> None:
    from .. import __version__

    doc = {
        "format": "smdinspect-batch-error",
        "version": 1,
        "smdinspect": __version__,
        "finished_utc": _utc_now(),
        "stack": job.name,
        "stack_dir": job.stack_dir,
        "exit_code": result.exit_code,
        "reason": result.reason,
        "input_sha256": result.input_sha256,
    }
    if result.detail:
        doc["traceback"] = result.detail
    _atomic.write_json(folder / ERROR_FILE, doc)


def record_error(job: BoardJob, result: BoardResult) -> None:
    """Install a report folder holding only ``error.json`` for a board whose worker
    never returned (crash, lost Dask worker); best effort."""
    out_dir = Path(job.out_dir)
    try:
        out_dir.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f"{PARTIAL_PREFIX}{out_dir.name}-", dir=out_dir.parent))
    except OSError:
        return
    try:
        os.chmod(tmp, 0o777 & ~_UMASK)
        _write_error(tmp, job, result)
        _install(tmp, out_dir)
    except OSError as exc:
        log.warning("cannot record the error of %s in %s: %s", job.name, out_dir, exc)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


def read_done_marker(out_dir: str | os.PathLike, *, input_sha256: str) -> BoardResult | None:
    """The recorded result of a finished board, or ``None`` if it must be (re)done.

    ``None`` unless ``out_dir`` holds a done-marker of this format whose input
    fingerprint equals ``input_sha256``, whose board did not error, and whose every
    listed output file still exists with the recorded SHA-256 (``report.json`` among
    them).
    """
    out_dir = Path(out_dir)
    try:
        doc = json.loads((out_dir / DONE_MARKER).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    try:
        if (doc.get("format") != MARKER_FORMAT or doc.get("version") != MARKER_VERSION
                or doc.get("input_sha256") != input_sha256):
            return None
        outputs = doc["outputs"]
        if "report.json" not in outputs:
            return None
        for rel, digest in outputs.items():
            if file_sha256(out_dir / rel) != digest:
                return None
        status = BoardStatus(doc["status"])
        if status is BoardStatus.ERROR:
            return None
        return BoardResult(
            stack=str(doc["stack"]), status=status, exit_code=int(doc["exit_code"]),
            joints=int(doc["joints"]), defects=int(doc["defects"]),
            unreliable=int(doc["unreliable"]), reason=str(doc["reason"]),
            seconds=float(doc["seconds"]), skipped=True, out_dir=str(out_dir),
            input_sha256=input_sha256,
        )
    except (OSError, KeyError, TypeError, ValueError, AttributeError):
        return None


def _install(tmp: Path, dest: Path) -> None:
    """Rename the finished folder ``tmp`` onto ``dest``, replacing an older one.

    ``dest`` is first renamed aside (to a ``.smdinspect-old-`` sibling) and removed
    after the new folder is in place. A crash between the two renames leaves no folder
    at ``dest`` (the board is redone by the next run) and never a mixed one.
    """
    old = None
    if dest.exists() or dest.is_symlink():
        old = Path(tempfile.mkdtemp(prefix=f"{OLD_PREFIX}{dest.name}-", dir=dest.parent))
        old.rmdir()
        os.rename(dest, old)
    os.rename(tmp, dest)
    _fsync_dir(dest.parent)
    if old is not None:
        if old.is_dir() and not old.is_symlink():
            shutil.rmtree(old, ignore_errors=True)
        else:
            old.unlink(missing_ok=True)


def _fsync_dir(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def clean_leftovers(reports_dir: str | os.PathLike) -> list[Path]:
    """Remove the temporary folders a killed run left under ``reports_dir``.

    Only folders named ``.smdinspect-partial-*`` or ``.smdinspect-old-*`` are removed
    (the caller holds the report folder's lock, so no running batch owns them).
    Returns the removed paths.
    """
    removed = []
    for dirpath, dirnames, _ in os.walk(reports_dir):
        keep = []
        for name in dirnames:
            if name.startswith((PARTIAL_PREFIX, OLD_PREFIX)):
                path = Path(dirpath) / name
                shutil.rmtree(path, ignore_errors=True)
                removed.append(path)
            else:
                keep.append(name)
        dirnames[:] = keep
    return removed
