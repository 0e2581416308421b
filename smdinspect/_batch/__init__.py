"""Machinery of ``smdinspect batch``; the public names are in :mod:`smdinspect.batch`."""

from ._discover import discover_stacks, file_sha256, stack_input_sha256
from ._job import (
    DONE_MARKER,
    ERROR_FILE,
    BoardJob,
    BoardResult,
    BoardStatus,
    clean_leftovers,
    read_done_marker,
    run_board,
)
from ._report import SUMMARY_COLUMNS, merge_junit, write_summary_csv, write_summary_json
from ._run import BatchResult, batch_exit_code, run_batch
from ._runners import DaskTLS, dask_client, run_dask, run_local

__all__ = [
    "DONE_MARKER",
    "ERROR_FILE",
    "SUMMARY_COLUMNS",
    "BatchResult",
    "BoardJob",
    "BoardResult",
    "BoardStatus",
    "DaskTLS",
    "batch_exit_code",
    "clean_leftovers",
    "dask_client",
    "discover_stacks",
    "file_sha256",
    "merge_junit",
    "read_done_marker",
    "run_batch",
    "run_board",
    "run_dask",
    "run_local",
    "stack_input_sha256",
    "write_summary_csv",
    "write_summary_json",
]
