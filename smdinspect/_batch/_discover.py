"""Find the stacks of a batch and fingerprint their inputs."""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any

from ..errors import InputError

__all__ = ["discover_stacks", "file_sha256", "stack_input_sha256"]

MANIFEST = "stack.json"
_CHUNK = 1 << 20


def discover_stacks(
    stacks_dir: str | os.PathLike, *, exclude: tuple[str | os.PathLike, ...] = ()
) -> list[tuple[str, Path]]:
    """Every stack directory (a folder holding ``stack.json``) under ``stacks_dir``.

    The search is recursive and follows symbolic links (each real folder is visited
    once). A stack directory is a leaf: folders inside it are not searched. Hidden
    folders (name starting with ``.``) and the folders in ``exclude`` (with everything
    under them) are skipped.

    Parameters
    ----------
    stacks_dir : path
        The folder to search. When it is itself a stack directory, the batch has one
        board, named after the folder.
    exclude : tuple of path
        Folders not to search (the batch's report folder when it lies inside
        ``stacks_dir``).

    Returns
    -------
    stacks : list of (name, path)
        ``name`` is the stack's path relative to ``stacks_dir`` in POSIX form (the
        board's report folder inside the batch's report folder); sorted by name.

    Raises
    ------
    InputError
        ``stacks_dir`` is not a folder.
    """
    root = Path(stacks_dir)
    if not root.is_dir():
        raise InputError(f"stacks folder not found: {root}")
    if (root / MANIFEST).is_file():
        return [(root.resolve().name, root)]
    skip = {Path(p).resolve() for p in exclude}
    seen: set[Path] = set()
    found: list[tuple[str, Path]] = []
    for dirpath, dirnames, filenames in os.walk(root, followlinks=True):
        here = Path(dirpath)
        real = here.resolve()
        if real in seen or real in skip:
            dirnames[:] = []
            continue
        seen.add(real)
        if here != root and MANIFEST in filenames:
            found.append((here.relative_to(root).as_posix(), here))
            dirnames[:] = []
            continue
        dirnames[:] = sorted(n for n in dirnames if not n.startswith("."))
    return sorted(found)


def file_sha256(path: str | os.PathLike) -> str:
    """Hex SHA-256 of a file's bytes, read in 1 MiB chunks."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while chunk := fh.read(_CHUNK):
            h.update(chunk)
    return h.hexdigest()


def stack_input_sha256(stack_dir: str | os.PathLike, *, board_sha256: str,
                       settings: dict[str, Any]) -> str:
    """Fingerprint of everything a board's reports depend on.

    SHA-256 over ``stack.json``, the name, size and bytes of every frame file it lists
    (in the listed order), the board file's SHA-256 and the settings (canonical JSON).
    A frame that is missing or unreadable enters as a marker, so a later fix changes
    the fingerprint. When ``stack.json`` cannot be parsed only its bytes enter (the
    inspection then fails and nothing is skipped on that basis).

    Raises
    ------
    OSError
        ``stack.json`` cannot be read.
    """
    stack_dir = Path(stack_dir)
    h = hashlib.sha256()
    h.update(b"smdinspect-batch-input/1\0")
    h.update(board_sha256.encode() + b"\0")
    h.update(json.dumps(settings, sort_keys=True, separators=(",", ":")).encode() + b"\0")
    manifest = (stack_dir / MANIFEST).read_bytes()
    h.update(hashlib.sha256(manifest).digest())
    try:
        frames = json.loads(manifest.decode("utf-8"))["frames"]
        names = [f["file"] for f in frames]
    except (ValueError, KeyError, TypeError):
        return h.hexdigest()
    for name in names:
        h.update(str(name).encode("utf-8", "replace") + b"\0")
        path = stack_dir / str(name)
        try:
            h.update(str(path.stat().st_size).encode() + b"\0")
            h.update(bytes.fromhex(file_sha256(path)))
        except OSError as exc:
            h.update(f"unreadable:{exc.errno}".encode())
    return h.hexdigest()
