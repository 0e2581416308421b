"""Atomic writes: a file is written to a temporary file in its folder, then renamed; a
folder of outputs is written to a temporary sibling folder, then swapped in.

A crash (even SIGKILL) never leaves a half-written file under the final name, nor a
mix of two runs' outputs in one folder. A full disk is one
:class:`~smdinspect.errors.OutputError`: "no space left on device: PATH".
"""

from __future__ import annotations

import contextlib
import errno
import json
import logging
import os
import re
import secrets
import shutil
import tempfile
from pathlib import Path
from typing import Any, Collection, Iterator

import numpy as np

from .errors import InputError, OutputError, SmdInspectError

__all__ = [
    "atomic_path",
    "replace_dir",
    "write_bytes",
    "write_image",
    "write_json",
    "write_text",
    "write_tiff",
]


log = logging.getLogger(__name__)

_UMASK = os.umask(0)
os.umask(_UMASK)
#: Less free space than this after a short write without an errno means the disk is full.
_FULL_BYTES = 2**20


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, *, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; rename it onto ``path`` on success.

    The temporary file keeps ``path``'s suffix (or ``suffix``) so writers that pick a
    format from the extension (OpenCV, Open3D, trimesh) still work.
    """
    path = Path(path)
    tmp_path = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(
            prefix=f".{path.stem}.", suffix=suffix or path.suffix or ".tmp", dir=path.parent
        )
        os.close(fd)
        tmp_path = Path(tmp)
        os.chmod(tmp_path, 0o666 & ~_UMASK)  # mkstemp makes 0600; give the usual permissions
        yield tmp_path
        with open(tmp_path, "rb+") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp_path, path)
    except OSError as exc:
        if not isinstance(exc, SmdInspectError) and _disk_full(exc, path.parent):
            raise OutputError(errno.ENOSPC, f"no space left on device: {path}") from exc
        raise
    finally:
        if tmp_path is not None and tmp_path.exists():
            tmp_path.unlink()


def _disk_full(exc: OSError, folder: Path) -> bool:
    """Whether ``exc`` from writing into ``folder`` means the device is full.

    Some writers report a short write without an errno (numpy's ``tofile``, used by
    tifffile: "16384 requested and 16316 written"; Open3D returns False): then the
    free space decides.
    """
    if exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return True
    if exc.errno is not None:
        return False
    try:
        st = os.statvfs(folder)
    except OSError:
        return False
    return st.f_bavail * st.f_frsize < _FULL_BYTES


def write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def write_text(path: str | os.PathLike, text: str) -> Path:
    """Write UTF-8 ``text`` to ``path`` atomically."""
    return write_bytes(path, text.encode("utf-8"))


def write_json(path: str | os.PathLike, obj: Any) -> Path:
    """Write ``obj`` as indented JSON to ``path`` atomically."""
    return write_text(path, json.dumps(obj, indent=2, default=_json_default) + "\n")


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"cannot write {type(obj).__name__} to JSON")


def write_image(path: str | os.PathLike, image: np.ndarray) -> Path:
    """Encode ``image`` with OpenCV by ``path``'s extension and write it atomically.

    Colour images are taken as RGB (the order smdinspect uses everywhere) and stored
    in the file's usual order.
    """
    import cv2

    path = Path(path)
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] == 3:
        img = cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2BGR)  # ~70x numpy's [..., ::-1]
    ok, buf = cv2.imencode(path.suffix or ".png", np.ascontiguousarray(img))
    if not ok:
        raise OSError(f"could not encode image for {path}")
    return write_bytes(path, buf.tobytes())


def write_tiff(path: str | os.PathLike, array: np.ndarray, **kwargs: Any) -> Path:
    """Write ``array`` as a TIFF (dtype kept, e.g. float32) atomically with tifffile."""
    import tifffile

    with atomic_path(path) as tmp:
        tifffile.imwrite(tmp, np.asarray(array), **kwargs)
    return Path(path)


# -- output folders -----------------------------------------------------------------------
@contextlib.contextmanager
def replace_dir(path: str | os.PathLike, *, replaces: Collection[str],
                carry: Collection[str] = ()) -> Iterator[Path]:
    """Yield an empty folder that replaces the folder ``path`` as a whole on success.

    The outputs of one run replace the earlier ones all together or not at all: they are
    written into a sibling ``.NAME.partial-PID-XXXX``; on success ``path`` (if any) is
    renamed aside to ``.NAME.old-PID-XXXX``, the sibling renamed onto ``path`` and the
    old folder deleted. On any error (Ctrl-C included) the sibling is deleted, ``path``
    is left as it was, and folders created to hold it are removed again. Siblings of a
    killed run (whose process is gone) are removed first; if it was killed between the
    two renames, its old folder is put back.

    Parameters
    ----------
    path : folder
        The output folder.
    replaces : collection of str
        File names earlier runs write into ``path``. A ``path`` holding anything else
        (the user's files, a stack) is refused before anything is written.
    carry : collection of str
        Files of the existing ``path`` the new folder starts with (hard links, or
        copies across file systems).

    Raises
    ------
    InputError
        ``path`` is a file, or holds files that are not earlier outputs.
    """
    out = Path(path)
    _check_replaceable(out, replaces)
    made = _make_folders(out.parent)
    _remove_stale(out)
    tmp = None
    try:
        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.partial-{os.getpid()}-", dir=out.parent))
        os.chmod(tmp, 0o777 & ~_UMASK)  # mkdtemp makes 0700
        for name in carry:
            if (out / name).is_file():
                _link_or_copy(out / name, tmp / name)
        yield tmp
        _swap_in(tmp, out)
    except BaseException as exc:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
        for folder in reversed(made):
            with contextlib.suppress(OSError):
                folder.rmdir()
        if tmp is not None and isinstance(exc, OutputError):
            raise OutputError(exc.errno, str(exc).replace(str(tmp), str(out))) from exc
        if not isinstance(exc, SmdInspectError) and isinstance(exc, OSError) \
                and _disk_full(exc, out.parent):
            raise OutputError(errno.ENOSPC, f"no space left on device: {out}") from exc
        raise


def _check_replaceable(out: Path, replaces: Collection[str]) -> None:
    if not out.exists():
        return
    if not out.is_dir():
        raise InputError(f"--out {out} exists and is not a directory")
    stems = {Path(n).stem for n in replaces}
    foreign = sorted(p.name for p in out.iterdir()
                     if p.name not in replaces and not _leftover(p.name, stems))
    if foreign:
        listed = ", ".join(foreign[:3]) + (", ..." if len(foreign) > 3 else "")
        raise InputError(f"--out {out} holds files smdinspect did not write there ({listed}); "
                         "the output folder is replaced as a whole: give a new or empty "
                         "folder, or one an earlier run wrote")


def _leftover(name: str, stems: set[str]) -> bool:
    """A temporary file or folder an interrupted write left (see atomic_path)."""
    return name.startswith(".partial-") or any(name.startswith(f".{s}.") for s in stems)


def _make_folders(folder: Path) -> list[Path]:
    """Create ``folder`` and its missing parents; return those created, outermost first."""
    missing = [p for p in (folder, *folder.parents) if not p.exists()][::-1]
    folder.mkdir(parents=True, exist_ok=True)
    return missing


_STALE = re.compile(r"^\.(?P<name>.+)\.(?P<kind>partial|old)-(?P<pid>\d+)-")


def _remove_stale(out: Path) -> None:
    """Remove the temporary siblings of ``out`` whose process no longer runs."""
    for p in sorted(out.parent.iterdir()):
        m = _STALE.match(p.name)
        if not m or m["name"] != out.name or not p.is_dir() or _alive(int(m["pid"])):
            continue
        if m["kind"] == "old" and not out.exists():
            log.warning("putting back %s, left aside by a run killed while swapping its "
                        "outputs in", out)
            os.replace(p, out)
            continue
        log.info("removing %s, left by a run that was killed", p)
        shutil.rmtree(p, ignore_errors=True)


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _link_or_copy(src: Path, dst: Path) -> None:
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


def _swap_in(new: Path, out: Path) -> None:
    if not out.exists():
        os.replace(new, out)
        return
    old = out.parent / f".{out.name}.old-{os.getpid()}-{secrets.token_hex(4)}"
    os.replace(out, old)
    try:
        os.replace(new, out)
    except BaseException:
        os.replace(old, out)
        raise
    shutil.rmtree(old, ignore_errors=True)
