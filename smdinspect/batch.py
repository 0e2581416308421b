"""Inspect many boards: a local process pool by default, a Dask cluster on request.

``run_batch(stacks_dir, board, out_dir)`` inspects every stack directory under
``stacks_dir`` against one reference board, writes each board's reports into
``out_dir/<stack path>/`` and a summary (CSV, JSON) plus one merged JUnit file into
``out_dir``. A bad stack fails only its board; reruns skip boards whose inputs did not
change; a killed run leaves no half-written report. See the README, "Many boards".

Examples
--------
>>> from smdinspect.batch import run_batch                      # doctest: +SKIP
>>> res = run_batch("stacks/", "references/demo_board.json", "reports/", workers=2)
>>> res.exit_code, res.counts()                                 # doctest: +SKIP
(1, {'ok': 3, 'defects': 1, 'error': 0, 'skipped': 0})
"""

from ._batch import (
    DONE_MARKER,
    SUMMARY_COLUMNS,
    BatchResult,
    BoardResult,
    BoardStatus,
    DaskTLS,
    discover_stacks,
    read_done_marker,
    run_batch,
    run_board,
    stack_input_sha256,
)

__all__ = [
    "DONE_MARKER",
    "SUMMARY_COLUMNS",
    "BatchResult",
    "BoardResult",
    "BoardStatus",
    "DaskTLS",
    "discover_stacks",
    "read_done_marker",
    "run_batch",
    "run_board",
    "stack_input_sha256",
]
