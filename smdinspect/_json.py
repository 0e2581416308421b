"""Reading the small JSON files smdinspect takes: stack.json, board files, settings.

Every way such a file can be bad - unreadable, not UTF-8, not JSON, ``NaN`` or
``Infinity``, nested deeper than Python's parser goes, or too big to be one of these
files - is one :class:`~smdinspect.errors.InputError` naming the file.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from .errors import InputError

__all__ = ["MAX_JSON_BYTES", "read_json"]

#: Largest JSON file read (a 2000-frame stack.json is about 0.3 MiB).
MAX_JSON_BYTES = 64 * 2**20


def read_json(path: str | os.PathLike) -> Any:
    """Parse the JSON file ``path``; every failure is an InputError ``"PATH: problem"``."""
    p = Path(path)
    try:
        size = p.stat().st_size
        if size > MAX_JSON_BYTES:
            raise InputError(f"{p}: {size / 2**20:.0f} MiB is too big for a JSON file of "
                             f"smdinspect (at most {MAX_JSON_BYTES // 2**20} MiB)")
        text = p.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise InputError(f"{p}: not UTF-8 text (byte {exc.start} is {exc.object[exc.start]:#04x})"
                         ) from None
    except OSError as exc:
        raise InputError(f"{p}: cannot read: {exc.strerror or exc}") from None
    try:
        return json.loads(text, parse_constant=_reject_constant)
    except json.JSONDecodeError as exc:
        raise InputError(f"{p}: not valid JSON: {exc.msg} at line {exc.lineno} "
                         f"column {exc.colno}") from None
    except RecursionError:
        raise InputError(f"{p}: not valid JSON here: nested too deeply") from None
    except ValueError as exc:  # _reject_constant
        raise InputError(f"{p}: not valid JSON: {exc}") from None


def _reject_constant(name: str) -> float:
    raise ValueError(f"{name} is not a valid number")
