"""Worker processes that do not outlive their parent."""

from __future__ import annotations

import sys

__all__ = ["die_with_parent"]


def die_with_parent() -> None:
    """Ask the kernel to SIGKILL this process when its parent dies (Linux
    ``PR_SET_PDEATHSIG``; a no-op elsewhere).

    Called in a pool process's initializer: a parent killed outright (SIGKILL, the OOM
    killer) cannot shut its pool down, and a ``spawn`` worker blocked on the task queue
    never sees it close, since its sibling workers hold the queue's other end; without
    this they would live on as orphans.
    """
    if not sys.platform.startswith("linux"):
        return
    try:
        import ctypes
        import signal

        libc = ctypes.CDLL(None, use_errno=True)
        pr_set_pdeathsig = 1
        libc.prctl(pr_set_pdeathsig, int(signal.SIGKILL), 0, 0, 0)
    except (OSError, AttributeError):  # pragma: no cover - exotic libc
        pass
