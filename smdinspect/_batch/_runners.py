"""Where the boards run: a local process pool, or a Dask distributed cluster.

Both take the same list of :class:`BoardJob` and call ``on_result`` once per job in
completion order. The job function is :func:`smdinspect._batch._job.run_board`; no
distribution logic of our own beyond handing jobs to the executor.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import multiprocessing
import os
import sys
import uuid
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from typing import Any, Callable, Iterator, Sequence

from ..errors import InputError
from ._job import BoardJob, BoardResult, BoardStatus, record_error, run_board

__all__ = ["dask_client", "run_dask", "run_local"]

log = logging.getLogger(__name__)

OnResult = Callable[[BoardResult], None]

#: ``dashboard_address=None`` switches the Bokeh dashboard off, but the scheduler still
#: serves a small HTTP endpoint (health, metrics) on port 8787 by default: put it on a
#: free port of 127.0.0.1 so that concurrent runs never collide.
LOCAL_CLUSTER_QUIET = {"dashboard_address": None,
                       "scheduler_kwargs": {"dashboard_address": "127.0.0.1:0"}}

_CRASH_REASON = ("the worker process died while inspecting this board (crash or out of "
                 "memory); it was retried alone and died again")


def _crashed(job: BoardJob, reason: str) -> BoardResult:
    """The result of a board whose worker never returned; its folder gets error.json."""
    result = BoardResult(stack=job.name, status=BoardStatus.ERROR, exit_code=2, joints=None,
                         defects=None, unreliable=None, reason=reason, seconds=0.0,
                         skipped=False, out_dir=job.out_dir)
    record_error(job, result)
    return result


def _init_worker(threads: int) -> None:
    """Pool-process initializer.

    * Die with the batch (Linux ``PR_SET_PDEATHSIG``), so that a killed batch leaves no
      orphan still writing reports.
    * Size the OpenMP / BLAS thread pools of libraries loaded later to this worker's
      share of the CPUs, as Dask's nanny does for its workers (variables the user set
      are respected); OpenCV and Open3D are sized per board by
      :func:`~smdinspect._batch._job.limit_native_threads`.
    """
    if sys.platform.startswith("linux"):
        try:
            import ctypes
            import signal

            libc = ctypes.CDLL(None, use_errno=True)
            pr_set_pdeathsig = 1
            libc.prctl(pr_set_pdeathsig, int(signal.SIGKILL), 0, 0, 0)
        except (OSError, AttributeError):  # pragma: no cover - exotic libc
            pass
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, str(threads))


def run_local(jobs: Sequence[BoardJob], *, workers: int, on_result: OnResult,
              threads: int = 1) -> None:
    """Run ``jobs`` in a ``concurrent.futures.ProcessPoolExecutor`` of ``workers``.

    Processes are started with ``spawn`` (no fork of a threaded parent); each sizes its
    native thread pools to ``threads`` (see :func:`_init_worker`). At most
    ``workers`` boards are in flight, so a crashed worker process (a segfault in a
    decoder, the OOM killer) can only take those boards down: the pool is rebuilt and
    each of them is retried alone; a board whose lone run crashes again is recorded as
    an error and the batch goes on.
    """
    ctx = multiprocessing.get_context("spawn")
    pending = collections.deque(jobs)
    suspects: collections.deque[BoardJob] = collections.deque()
    def new_pool() -> ProcessPoolExecutor:
        return ProcessPoolExecutor(max_workers=workers, mp_context=ctx,
                                   initializer=_init_worker, initargs=(threads,))

    pool = new_pool()
    inflight: dict[Future, tuple[BoardJob, bool]] = {}
    try:
        while pending or suspects or inflight:
            if suspects:
                if not inflight:  # a suspect runs alone
                    job = suspects.popleft()
                    inflight[pool.submit(run_board, job)] = (job, True)
            else:
                while pending and len(inflight) < workers:
                    job = pending.popleft()
                    inflight[pool.submit(run_board, job)] = (job, False)
            done, _ = wait(list(inflight), return_when=FIRST_COMPLETED)
            broken = False
            for fut in done:
                job, alone = inflight.pop(fut)
                try:
                    result = fut.result()
                except BrokenProcessPool:
                    broken = True
                    if alone:
                        on_result(_crashed(job, _CRASH_REASON))
                    else:
                        log.warning("a worker process died; retrying %s alone", job.name)
                        suspects.append(job)
                    continue
                except Exception as exc:  # e.g. a result that cannot be unpickled
                    result = _crashed(job, f"the worker failed: {type(exc).__name__}: {exc}")
                on_result(result)
            if broken:
                # Every other in-flight future of the dead pool fails too: collect them.
                for fut, (job, alone) in list(inflight.items()):
                    try:
                        result = fut.result()
                    except BrokenProcessPool:
                        if alone:
                            on_result(_crashed(job, _CRASH_REASON))
                        else:
                            suspects.append(job)
                        continue
                    except Exception as exc:
                        result = _crashed(job, f"the worker failed: {type(exc).__name__}: {exc}")
                    on_result(result)
                inflight.clear()
                pool.shutdown(wait=True, cancel_futures=True)
                pool = new_pool()
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def _worker_version() -> str:
    """Runs on each Dask worker: the smdinspect version it imports."""
    import smdinspect

    return smdinspect.__version__


@contextlib.contextmanager
def dask_client(*, scheduler: str | None = None, local_workers: int | None = None,
                connect_timeout_s: float = 30.0) -> Iterator[tuple[Any, str]]:
    """Connect to (or start) a Dask distributed cluster and check its workers.

    Parameters
    ----------
    scheduler : str, optional
        Address of an existing scheduler (``tcp://HOST:8786``). Its workers must import
        the same smdinspect version (checked here) and see the same file system.
    local_workers : int, optional
        Instead: start a ``LocalCluster`` of this many single-threaded worker processes
        on 127.0.0.1 (dashboard off), closed on exit.
    connect_timeout_s : float
        How long to wait for the scheduler and for a first worker.

    Yields
    ------
    (client, description)
        A ``distributed.Client`` and a description of the executor for the summary.

    Raises
    ------
    InputError
        The scheduler cannot be reached, no worker joins, or a worker cannot import
        smdinspect or runs another version.
    """
    try:
        from distributed import Client, LocalCluster
    except ImportError as exc:  # pragma: no cover - dask[distributed] is a dependency
        raise InputError(f"Dask is not installed ({exc}); "
                         "pip install 'dask[distributed]'") from None
    from .. import __version__

    cluster = None
    if local_workers is not None:
        cluster = LocalCluster(n_workers=local_workers, threads_per_worker=1, processes=True,
                               host="127.0.0.1", **LOCAL_CLUSTER_QUIET)
        client = Client(cluster)
        where = f"dask-local({local_workers} workers)"
    else:
        try:
            client = Client(scheduler, timeout=f"{connect_timeout_s}s")
        except (OSError, TimeoutError) as exc:
            raise InputError(f"cannot connect to the Dask scheduler at {scheduler}: "
                             f"{exc}") from None
        where = f"dask({scheduler})"
    try:
        try:
            client.wait_for_workers(1, timeout=connect_timeout_s)
        except TimeoutError:
            raise InputError(f"no Dask worker joined {scheduler} within "
                             f"{connect_timeout_s:g} s") from None
        try:
            versions = client.run(_worker_version)
        except Exception as exc:
            raise InputError("Dask workers cannot import smdinspect "
                             f"({type(exc).__name__}: {exc}); install it in the workers' "
                             "environment") from None
        wrong = {w: v for w, v in versions.items() if v != __version__}
        if wrong:
            w, v = next(iter(wrong.items()))
            raise InputError(f"Dask worker {w} runs smdinspect {v}, this client {__version__}; "
                             "install the same version on every worker")
        yield client, where
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def run_dask(jobs: Sequence[BoardJob], *, client: Any, on_result: OnResult) -> None:
    """Run ``jobs`` on a Dask cluster: one ``client.submit`` task per board, results
    handed to ``on_result`` as they complete (``distributed.as_completed``).

    A task that fails outside :func:`run_board` (a worker lost more often than Dask's
    ``allowed-failures``, a result that cannot be unpickled) becomes an ``error`` row.
    """
    from distributed import as_completed

    token = uuid.uuid4().hex[:8]
    futures = {}
    for job in jobs:
        fut = client.submit(run_board, job, key=f"smdinspect-board-{job.name}-{token}",
                            pure=False)
        futures[fut] = job
    try:
        for fut in as_completed(list(futures)):
            job = futures[fut]
            try:
                result = fut.result()
            except Exception as exc:  # KilledWorker, a lost worker, unpickling errors...
                result = _crashed(job, f"the Dask task failed: {type(exc).__name__}: {exc}")
            on_result(result)
            fut.release()
    finally:
        client.cancel([f for f in futures if not f.done()])
