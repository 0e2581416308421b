"""Where the boards run: a local process pool, or a Dask distributed cluster.

Both take the same list of :class:`BoardJob` and call ``on_result`` once per job in
completion order, and ``on_progress(stack, stage, done, total)`` as each running board
moves (frames reconstructed, then measuring and writing its reports). The job function
is :func:`smdinspect._batch._job.run_board`; no distribution logic of our own beyond
handing jobs to the executor.

Security of the Dask cluster
----------------------------
A local cluster (``--dask-local``) is started with mutual TLS: a key and self-signed
certificate generated in memory for this run (``distributed.security.Security.temporary``)
that the scheduler, the workers and our client present to each other, so another user of
the machine cannot connect to the scheduler (or a worker) and run code as the batch's
user. Its scratch space is a private folder (``tempfile.mkdtemp``, mode 0700) removed
afterwards, never the shared, predictable ``$TMPDIR/dask-scratch-space``; the scheduler and
workers serve only the health check over HTTP (no task or log pages).
An existing cluster (``--scheduler tls://HOST:8786``) is reached with the certificate files
of :class:`DaskTLS` (or Dask's own ``distributed.comm.tls`` settings).
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import logging
import multiprocessing
import os
import queue as queue_mod
import shutil
import tempfile
import threading
import uuid
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

from .._proc import die_with_parent
from ..errors import InputError
from . import _job
from ._job import BoardJob, BoardResult, BoardStatus, record_error, run_board

__all__ = ["DaskTLS", "dask_client", "run_dask", "run_local"]

log = logging.getLogger(__name__)

OnResult = Callable[[BoardResult], None]
#: ``on_progress(stack, stage, done, total)``; see :data:`smdinspect._batch._job.STAGES`.
OnProgress = Callable[[str, str, int, int], None]

#: HTTP routes the local cluster's scheduler and workers serve: the health check only
#: (Dask's default also serves task, worker and log pages to anyone who can connect).
_LOCAL_HTTP_ROUTES = ["distributed.http.health"]


@dataclass(frozen=True)
class DaskTLS:
    """Certificate files for a TLS Dask scheduler (``tls://HOST:PORT``).

    Attributes
    ----------
    ca_file : path
        PEM file of the certificate authority that signed the scheduler's and workers'
        certificates (for a self-signed cluster certificate: that certificate).
    cert_file : path
        PEM certificate this client presents (Dask clusters require client certificates).
    key_file : path, optional
        PEM private key of ``cert_file``, when it is not in the same file.
    """

    ca_file: str
    cert_file: str
    key_file: str | None = None

    def __post_init__(self) -> None:
        for name in ("ca_file", "cert_file", "key_file"):
            value = getattr(self, name)
            if value is None and name == "key_file":
                continue
            if not isinstance(value, (str, os.PathLike)) or not str(value):
                raise InputError(f"DaskTLS {name} must be a file path; got {value!r}")
            path = Path(value)
            if not path.is_file():
                raise InputError(f"TLS {name.replace('_file', '')} file not found: {path}")
            try:
                with open(path, "rb") as fh:
                    fh.read(1)
            except OSError as exc:
                raise InputError(f"cannot read the TLS {name.replace('_file', '')} file "
                                 f"{path}: {exc.strerror or exc}") from None
            object.__setattr__(self, name, str(path.resolve()))

    def security(self) -> Any:
        """The ``distributed.security.Security`` of a client using these files."""
        from distributed.security import Security

        return Security(tls_ca_file=self.ca_file, tls_client_cert=self.cert_file,
                        tls_client_key=self.key_file, require_encryption=True)

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


def _init_worker(threads: int, progress_queue: Any = None) -> None:
    """Pool-process initializer.

    * Send the progress of its boards to the parent through ``progress_queue`` (a
      ``multiprocessing`` queue; its feeder thread is never waited for at exit, so a
      parent that stopped reading cannot hang the worker).

    * Die with the batch (Linux ``PR_SET_PDEATHSIG``), so that a killed batch leaves no
      orphan still writing reports.
    * Size the OpenMP / BLAS thread pools of libraries loaded later to this worker's
      share of the CPUs, as Dask's nanny does for its workers (variables the user set
      are respected); OpenCV and Open3D are sized per board by
      :func:`~smdinspect._batch._job.limit_native_threads`.
    """
    die_with_parent()
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, str(threads))
    if progress_queue is not None:
        progress_queue.cancel_join_thread()
        _job.set_progress_sink(progress_queue.put_nowait)


class _ProgressListener:
    """A thread in the parent that hands the pool's progress messages to a callback."""

    def __init__(self, q: Any, on_progress: OnProgress) -> None:
        self.q, self.on_progress = q, on_progress
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._run, name="smdinspect-progress",
                                       daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                msg = self.q.get(timeout=0.1)
            except queue_mod.Empty:
                continue
            except (EOFError, OSError, ValueError):  # the queue was closed
                return
            try:
                self.on_progress(*msg)
            except Exception:  # a progress display must never stop the batch
                log.debug("progress callback failed", exc_info=True)

    def stop(self) -> None:
        self._stop.set()
        self.thread.join(timeout=2)
        self.q.close()
        self.q.cancel_join_thread()


def run_local(jobs: Sequence[BoardJob], *, workers: int, on_result: OnResult,
              threads: int = 1, on_progress: OnProgress | None = None) -> None:
    """Run ``jobs`` in a ``concurrent.futures.ProcessPoolExecutor`` of ``workers``
    processes (one board per process at a time).

    Processes are started with ``spawn`` (no fork of a threaded parent); each sizes its
    native thread pools to ``threads`` (see :func:`_init_worker`). At most
    ``workers`` boards are in flight, so a crashed worker process (a segfault in a
    decoder, the OOM killer) can only take those boards down: the pool is rebuilt and
    each of them is retried alone; a board whose lone run crashes again is recorded as
    an error and the batch goes on.

    ``on_progress`` (called from a listener thread) gets each running board's stages;
    every pool gets a fresh queue, so a worker killed while writing to it cannot block
    the progress of the next pool.
    """
    ctx = multiprocessing.get_context("spawn")
    pending = collections.deque(jobs)
    suspects: collections.deque[BoardJob] = collections.deque()
    listener: _ProgressListener | None = None

    def new_pool() -> ProcessPoolExecutor:
        nonlocal listener
        q = None
        if on_progress is not None:
            if listener is not None:
                listener.stop()
            q = ctx.Queue()
            listener = _ProgressListener(q, on_progress)
        return ProcessPoolExecutor(max_workers=workers, mp_context=ctx,
                                   initializer=_init_worker, initargs=(threads, q))

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
        if listener is not None:
            listener.stop()


def _worker_version() -> str:
    """Runs on each Dask worker: the smdinspect version it imports."""
    import smdinspect

    return smdinspect.__version__


def _check_address(scheduler: str, tls: DaskTLS | None) -> str:
    """The address to connect to; a TLS address needs certificates, certificates a TLS
    address (a plain ``HOST:PORT`` gets the scheme of the certificates)."""
    addr = scheduler.strip()
    scheme = addr.split("://", 1)[0].lower() if "://" in addr else ""
    if tls is not None:
        if not scheme:
            return f"tls://{addr}"
        if scheme != "tls":
            raise InputError(f"TLS certificates were given but the scheduler address {addr} "
                             "is not tls://; use tls://HOST:PORT")
        return addr
    if scheme == "tls":
        import dask

        if not (dask.config.get("distributed.comm.tls.ca-file", None)
                and dask.config.get("distributed.comm.tls.client.cert", None)):
            raise InputError(f"the scheduler {addr} uses TLS: give its CA file and a client "
                             "certificate (--tls-ca-file, --tls-cert, --tls-key) or set "
                             "Dask's distributed.comm.tls settings")
    return addr


@contextlib.contextmanager
def _private_local_cluster(n_workers: int) -> Iterator[tuple[Any, Path]]:
    """A ``LocalCluster`` on 127.0.0.1 with mutual TLS (a key and self-signed
    certificate generated for this run), a private scratch folder and only the health
    check over HTTP. Yields ``(cluster, scratch_dir)``; both are gone afterwards."""
    import dask
    from distributed import LocalCluster

    try:
        from distributed.security import Security

        security = Security.temporary()
    except ImportError as exc:  # cryptography missing
        raise InputError(f"--dask-local needs the 'cryptography' package for its TLS "
                         f"certificate ({exc}); pip install cryptography") from None
    scratch = Path(tempfile.mkdtemp(prefix="smdinspect-dask-"))  # mode 0700
    try:
        with dask.config.set({
            # every Dask server of this cluster (the scheduler too) puts its scratch here
            "temporary-directory": str(scratch),
            "distributed.scheduler.http.routes": _LOCAL_HTTP_ROUTES,
            "distributed.worker.http.routes": _LOCAL_HTTP_ROUTES,
        }):
            cluster = LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True,
                                   host="127.0.0.1", protocol="tls://", security=security,
                                   local_directory=str(scratch), **LOCAL_CLUSTER_QUIET)
            try:
                yield cluster, scratch
            finally:
                cluster.close()
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


@contextlib.contextmanager
def dask_client(*, scheduler: str | None = None, local_workers: int | None = None,
                tls: DaskTLS | None = None,
                connect_timeout_s: float = 30.0) -> Iterator[tuple[Any, str]]:
    """Connect to (or start) a Dask distributed cluster and check its workers.

    Parameters
    ----------
    scheduler : str, optional
        Address of an existing scheduler (``tcp://HOST:8786``, or ``tls://HOST:8786``
        with ``tls``). Its workers must import the same smdinspect version (checked
        here) and see the same file system.
    local_workers : int, optional
        Instead: start a ``LocalCluster`` of this many single-threaded worker processes
        on 127.0.0.1, closed on exit: mutual TLS with a certificate generated for this
        run, a private scratch folder, dashboard off (see the module docstring).
    tls : DaskTLS, optional
        Certificate files for a ``tls://`` scheduler. Without them a ``tls://`` address
        needs Dask's ``distributed.comm.tls`` configuration.
    connect_timeout_s : float
        How long to wait for the scheduler and for a first worker.

    Yields
    ------
    (client, description)
        A ``distributed.Client`` and a description of the executor for the summary.

    Raises
    ------
    InputError
        The scheduler cannot be reached (or refuses our certificate), no worker joins,
        or a worker cannot import smdinspect or runs another version.
    """
    try:
        from distributed import Client
    except ImportError as exc:  # pragma: no cover - dask[distributed] is a dependency
        raise InputError(f"Dask is not installed ({exc}); "
                         "pip install 'dask[distributed]'") from None
    from .. import __version__

    with contextlib.ExitStack() as stack:
        if local_workers is not None:
            cluster, _ = stack.enter_context(_private_local_cluster(local_workers))
            client = Client(cluster)
            where = f"dask-local({local_workers} workers, tls)"
        else:
            address = _check_address(scheduler, tls)
            kwargs = {"security": tls.security()} if tls is not None else {}
            try:
                client = Client(address, timeout=f"{connect_timeout_s}s", **kwargs)
            except (OSError, TimeoutError) as exc:
                hint = ("; is it a TLS scheduler (tls://) and are these its certificates?"
                        if tls is not None or address.startswith("tls://") else "")
                raise InputError(f"cannot connect to the Dask scheduler at {address}: "
                                 f"{exc}{hint}") from None
            where = f"dask({address})"
        stack.callback(client.close)
        try:
            client.wait_for_workers(1, timeout=connect_timeout_s)
        except TimeoutError:
            raise InputError(f"no Dask worker joined {where} within "
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


def run_dask(jobs: Sequence[BoardJob], *, client: Any, on_result: OnResult,
             on_progress: OnProgress | None = None) -> None:
    """Run ``jobs`` on a Dask cluster: one ``client.submit`` task per board, results
    handed to ``on_result`` as they complete (``distributed.as_completed``).

    A task that fails outside :func:`run_board` (a worker lost more often than Dask's
    ``allowed-failures``, a result that cannot be unpickled) becomes an ``error`` row.
    ``on_progress`` gets the boards' stages, sent by the workers as Dask events on a
    topic of this run (``Worker.log_event`` → ``Client.subscribe_topic``).
    """
    from distributed import as_completed

    token = uuid.uuid4().hex[:8]
    topic = ""
    if on_progress is not None:
        topic = f"smdinspect-progress-{token}"

        def handler(event: Any) -> None:
            try:
                _, msg = event
                on_progress(*msg)
            except Exception:  # a progress display must never stop the batch
                log.debug("progress callback failed", exc_info=True)

        client.subscribe_topic(topic, handler)
        jobs = [dataclasses.replace(j, progress_topic=topic) for j in jobs]
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
        if topic:
            with contextlib.suppress(Exception):
                client.unsubscribe_topic(topic)
