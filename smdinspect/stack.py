"""The focal stack: on-disk format, streaming frame reader, validation, writer.

A stack is a directory holding ``stack.json`` and one image per frame::

    {
      "format": "smdinspect-stack",
      "version": 1,
      "pixel_size_mm": 0.015,
      "frames": [{"file": "frame_0000.png", "z_mm": 0.00},
                 {"file": "frame_0001.png", "z_mm": 0.05}],
      "optics": {...},            # optional, free-form (see smdinspect.optics)
      "rig": {"d_mm": 120.0, "d_f_mm": 110.0, "step_mm": 0.05}   # optional
    }

``z_mm`` is the height of the frame's focused plane above the board plane, growing
towards the camera. A frame without ``z_mm`` gets ``h_n = d - (d_f + n*step)`` from the
rig block (``n`` is the frame's ``"n"`` key, else its position in the list). Unknown keys
are ignored; a missing ``version`` means 1; frames may be listed in either z order (they
are served in ascending z).

Frames are read one at a time (:meth:`FocalStack.iter_frames`), never all at once.
Images are returned as stored: ``uint8``/``uint16``/``float32``, grey ``(H, W)`` or RGB
``(H, W, 3)``; no rescaling. Every frame of a stack must have the first frame's pixel
type (8-bit, 16-bit or float): one 16-bit frame among 8-bit ones is an error, not a
frame that outshines the others.
"""

from __future__ import annotations

import json
import logging
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator, Sequence

import numpy as np

from . import _atomic
from ._json import read_json
from .errors import InputError

__all__ = [
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "IMAGE_SUFFIXES",
    "FocalStack",
    "Frame",
    "StackWriter",
    "open_stack",
    "read_image",
]

FORMAT_NAME = "smdinspect-stack"
FORMAT_VERSION = 1
MANIFEST = "stack.json"
IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".jpg", ".jpeg", ".bmp")
#: Accepted object-side pixel sizes (mm): 1 nm to 10 mm.
PIXEL_SIZE_RANGE_MM = (1e-6, 10.0)
#: Largest accepted |z_mm| of a frame (mm).
MAX_ABS_Z_MM = 1e4

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Frame:
    """One frame of a stack: its image file and the height of its focused plane."""

    path: Path
    z_mm: float


@dataclass(frozen=True)
class FocalStack:
    """A validated focal stack, frames sorted by ascending ``z_mm``.

    Attributes
    ----------
    frames : tuple of Frame
        Ascending in ``z_mm``, strictly.
    pixel_size_mm : float or None
        Object-side size of one pixel; ``None`` when unknown (x, y then in pixels).
    root : Path or None
        The stack directory (``None`` for a plain list of images).
    optics, rig, meta : dict
        Optional parameters carried through from the manifest.
    """

    frames: tuple[Frame, ...]
    pixel_size_mm: float | None = None
    root: Path | None = None
    optics: dict[str, Any] = field(default_factory=dict)
    rig: dict[str, Any] = field(default_factory=dict)
    meta: dict[str, Any] = field(default_factory=dict)
    # pixel type of the first frame decoded, and its path: every frame must match it
    _first_kind: dict[str, Any] = field(default_factory=dict, init=False, repr=False,
                                        compare=False)

    def __post_init__(self) -> None:
        if len(self.frames) < 3:
            raise InputError(f"a focal stack needs at least 3 frames; got {len(self.frames)}")
        z = np.array([f.z_mm for f in self.frames], dtype=np.float64)
        if not np.all(np.isfinite(z)):
            bad = next(f for f in self.frames if not math.isfinite(f.z_mm))
            raise InputError(f"frame {bad.path.name} has a non-finite z_mm: {bad.z_mm}")
        if np.any(np.abs(z) > MAX_ABS_Z_MM):
            bad = next(f for f in self.frames if abs(f.z_mm) > MAX_ABS_Z_MM)
            raise InputError(f"frame {bad.path.name} has z_mm {bad.z_mm:g}; heights must lie "
                             f"within ±{MAX_ABS_Z_MM:g} mm")
        if np.any(np.diff(z) <= 0):
            raise InputError("frames must be sorted by strictly increasing z_mm")
        lo, hi = PIXEL_SIZE_RANGE_MM
        if self.pixel_size_mm is not None and not lo <= self.pixel_size_mm <= hi:
            raise InputError(f"pixel_size_mm must be between {lo:g} and {hi:g} mm; "
                             f"got {self.pixel_size_mm:g}")

    # -- construction ---------------------------------------------------------------
    @classmethod
    def open(cls, root: str | os.PathLike) -> "FocalStack":
        """Open a stack directory (``root/stack.json``)."""
        root = Path(root)
        manifest = root / MANIFEST
        if not root.is_dir():
            raise InputError(f"no such folder: {root}")
        if not manifest.is_file():
            raise InputError(f"{root} has no {MANIFEST}; pass image files and --step-mm instead")
        return cls.from_manifest(read_json(manifest), root)

    @classmethod
    def from_manifest(cls, doc: Any, root: str | os.PathLike) -> "FocalStack":
        """Build a stack from a parsed ``stack.json`` document whose frames live in ``root``."""
        root = Path(root)
        if not isinstance(doc, dict):
            raise InputError(f"{MANIFEST} must hold a JSON object; got {type(doc).__name__}")
        version = doc.get("version", 1)
        if not isinstance(version, int) or version < 1 or version > FORMAT_VERSION:
            raise InputError(
                f"{MANIFEST}: unsupported format version {version!r}; this smdinspect reads "
                f"versions 1..{FORMAT_VERSION}"
            )
        frames_doc = doc.get("frames")
        if not isinstance(frames_doc, list):
            raise InputError(f"{MANIFEST}: 'frames' must be a list of {{file, z_mm}} objects")
        rig, optics, meta = (_object(doc, key) for key in ("rig", "optics", "meta"))
        frames = []
        for i, entry in enumerate(frames_doc):
            if not isinstance(entry, dict) or not isinstance(entry.get("file"), str):
                raise InputError(f"{MANIFEST}: frames[{i}] must be an object with a 'file' string")
            path = _inside(root, entry["file"], i)
            z = entry.get("z_mm")
            if z is None:
                z = _z_from_rig(rig, entry.get("n", i), i)
            frames.append(Frame(path, _finite_number(z, f"frames[{i}].z_mm")))
        pixel = doc.get("pixel_size_mm")
        if pixel is not None:
            pixel = _finite_number(pixel, "pixel_size_mm")
        return cls._sorted(
            frames,
            pixel_size_mm=pixel,
            root=root,
            optics=optics,
            rig=rig,
            meta=meta,
        )

    @classmethod
    def from_images(
        cls,
        paths: Sequence[str | os.PathLike],
        *,
        step_mm: float,
        pixel_size_mm: float | None = None,
        z0_mm: float = 0.0,
    ) -> "FocalStack":
        """A stack from image files in focus order, ``step_mm`` apart.

        A negative ``step_mm`` says the list runs from high to low focus (nearest focus
        first). The lowest frame is placed at ``z0_mm``.
        """
        step = _finite_number(step_mm, "step_mm")
        if step == 0:
            raise InputError("step_mm must be non-zero; got 0")
        paths = _frame_files(paths)
        low = min(0.0, (len(paths) - 1) * step)
        frames = [Frame(p, round(z0_mm + n * step - low, 12)) for n, p in enumerate(paths)]
        return cls._sorted(frames, pixel_size_mm=pixel_size_mm, root=None)

    @classmethod
    def from_named_images(
        cls,
        paths: Sequence[str | os.PathLike],
        *,
        pattern: str,
        pixel_size_mm: float | None = None,
    ) -> "FocalStack":
        """A stack from image files whose names hold their z (mm).

        ``pattern`` is a regular expression searched in each file name; its first group
        (the whole match if it has none) is the frame's z, e.g. ``Z(-?[0-9.]+)`` for
        ``XP005_Z-020.jpg`` (z = −20 mm). Frames are put in z order whatever their names'
        order.
        """
        try:
            rx = re.compile(pattern)
        except re.error as exc:
            raise InputError(f"--z-from-name: not a regular expression ({exc}): {pattern!r}") from None
        frames = []
        for p in _frame_files(paths):
            m = rx.search(p.name)
            if m is None:
                raise InputError(f"{p.name}: --z-from-name {pattern!r} does not match the file name")
            text = m.group(1) if rx.groups else m.group(0)
            try:
                z = float(text)
            except (TypeError, ValueError):
                raise InputError(f"{p.name}: --z-from-name {pattern!r} found {text!r}, "
                                 "not a number of mm") from None
            if not math.isfinite(z):
                raise InputError(f"{p.name}: z {text!r} is not a finite number of mm")
            frames.append(Frame(p, z))
        frames.sort(key=lambda f: f.z_mm)
        return cls._sorted(frames, pixel_size_mm=pixel_size_mm, root=None)

    @classmethod
    def _sorted(cls, frames: list[Frame], **kwargs: Any) -> "FocalStack":
        z = np.array([f.z_mm for f in frames])
        if len(frames) >= 2:
            d = np.diff(z)
            if np.any(d == 0):
                i = int(np.flatnonzero(d == 0)[0])
                raise InputError(f"duplicate z_mm {z[i]} for frames {frames[i].path.name} and "
                                 f"{frames[i + 1].path.name}")
            if not (np.all(d > 0) or np.all(d < 0)):
                raise InputError("frame z_mm values are not monotonic; list frames in focus order")
            if d[0] < 0:
                frames = frames[::-1]
        return cls(tuple(frames), **kwargs)

    # -- access -----------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.frames)

    @property
    def z_mm(self) -> np.ndarray:
        """``(n_frames,) float64``: focused-plane height of every frame, ascending."""
        return np.array([f.z_mm for f in self.frames], dtype=np.float64)

    @property
    def step_mm(self) -> float:
        """Median spacing between consecutive frames in mm."""
        return round(float(np.median(np.diff(self.z_mm))), 12)  # no 0.05000000000000001

    def read_frame(self, index: int) -> np.ndarray:
        """Decode frame ``index`` (see :func:`read_image`).

        Raises
        ------
        InputError
            The frame is unreadable, or its pixel type differs from the first frame
            decoded (frames of one stack share one bit depth).
        """
        path = self.frames[index].path
        image = read_image(path)
        first_dtype, first_path = self._first_kind.setdefault("kind", (image.dtype, path))
        if image.dtype != first_dtype:
            raise InputError(f"frame {path.name} is {_depth(image.dtype)} but {first_path.name} "
                             f"is {_depth(first_dtype)}; all frames of a stack must have one "
                             "bit depth")
        return image

    def iter_frames(self) -> Iterator[tuple[int, float, np.ndarray]]:
        """Yield ``(index, z_mm, image)`` one frame at a time, ascending z."""
        for i, f in enumerate(self.frames):
            yield i, f.z_mm, self.read_frame(i)


def _frame_files(paths: Sequence[str | os.PathLike]) -> list[Path]:
    """The listed frame files as Paths; InputError naming the first that is missing."""
    out = [Path(p) for p in paths]
    for p in out:
        if not p.is_file():
            raise InputError(f"frame file not found: {p}")
    return out


def open_stack(
    inputs: Sequence[str | os.PathLike],
    *,
    step_mm: float | None = None,
    pixel_size_mm: float | None = None,
    z_from_name: str | None = None,
) -> FocalStack:
    """Open what a user passed on the command line.

    One directory with ``stack.json`` opens as a stack; one directory without it, or a
    list of image files, needs ``step_mm`` (images in a directory are taken in name order)
    or ``z_from_name``, a regular expression finding each frame's z in its file name
    (:meth:`FocalStack.from_named_images`).
    """
    paths = [Path(p) for p in inputs]
    if not paths:
        raise InputError("no stack given: pass a stack directory or image files")
    if pixel_size_mm is not None:
        _finite_number(pixel_size_mm, "--pixel-size-mm")
    folder = None
    if len(paths) == 1 and paths[0].suffix.lower() not in IMAGE_SUFFIXES:
        folder = paths[0]
        if not folder.is_dir():
            raise InputError(f"no such folder: {folder}")
        if (folder / MANIFEST).is_file():
            if z_from_name is not None:
                raise InputError(f"{folder} has {MANIFEST} (its frames' z are recorded): "
                                 "--z-from-name is for image files")
            stack = FocalStack.open(folder)
            if pixel_size_mm is not None:
                stack = _replace_pixel(stack, pixel_size_mm)
            return stack
        paths = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not paths:
            raise InputError(f"{folder} has neither {MANIFEST} nor image files")
    if z_from_name is not None:
        if step_mm is not None:
            raise InputError("give --step-mm or --z-from-name, not both")
        return FocalStack.from_named_images(paths, pattern=z_from_name,
                                            pixel_size_mm=pixel_size_mm)
    if step_mm is None:
        what = (f"{folder} has no {MANIFEST}; its {len(paths)} images" if folder is not None
                else "a list of images")
        raise InputError(f"{what} need --step-mm (the focus step between frames) or "
                         "--z-from-name (a pattern finding each frame's z in its name)")
    stack = FocalStack.from_images(paths, step_mm=step_mm, pixel_size_mm=pixel_size_mm)
    if folder is not None:
        log.info("%s has no %s: taking its %d images %s .. %s in name order as frames %g mm "
                 "apart (%s)", folder, MANIFEST, len(paths), paths[0].name, paths[-1].name,
                 step_mm, "first is the lowest focus" if step_mm > 0 else "first is the highest focus")
    return stack


def _replace_pixel(stack: FocalStack, pixel_size_mm: float) -> FocalStack:
    from dataclasses import replace

    return replace(stack, pixel_size_mm=_finite_number(pixel_size_mm, "pixel_size_mm"))


def read_image(path: str | os.PathLike) -> np.ndarray:
    """Decode one image file without rescaling.

    Returns
    -------
    image : (H, W) or (H, W, 3) uint8, uint16 or float32
        RGB channel order for colour; an alpha channel is dropped.

    Raises
    ------
    InputError
        The file is missing, unreadable, truncated or of an unsupported depth.
    """
    import cv2

    path = Path(path)
    try:
        data = np.fromfile(path, dtype=np.uint8)
    except OSError as exc:
        raise InputError(f"cannot read frame {path}: {exc.strerror or exc}") from None
    if data.size == 0:
        raise InputError(f"frame {path} is empty")
    if _looks_truncated(data):
        raise InputError(f"frame {path} is truncated")
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(f"frame {path} is not a readable image (or is truncated)")
    if img.dtype not in (np.uint8, np.uint16, np.float32):
        raise InputError(f"frame {path} has unsupported pixel type {img.dtype}")
    if img.ndim == 3:
        if img.shape[2] == 1:
            img = img[:, :, 0]
        else:  # BGR(A) -> RGB: OpenCV's swap is ~70x numpy's reversed-stride copy
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGB if img.shape[2] == 4 else cv2.COLOR_BGR2RGB)
    return img


def _looks_truncated(data: np.ndarray) -> bool:
    """Cheap end-of-file checks for formats whose decoders tolerate truncation."""
    head = data[:8].tobytes()
    tail = data[-12:].tobytes()
    if head[:2] == b"\xff\xd8":  # JPEG must end with EOI (allow trailing padding)
        return b"\xff\xd9" not in data[-64:].tobytes()
    if head == b"\x89PNG\r\n\x1a\n":  # PNG must end with IEND
        return b"IEND" not in tail
    return False


def _inside(root: Path, name: str, i: int) -> Path:
    rel = Path(name)
    if rel.is_absolute() or name.startswith(("/", "\\")):
        raise InputError(f"{MANIFEST}: frames[{i}].file {name!r} is absolute; it must be "
                         "relative to the stack folder")
    resolved = (root / rel).resolve()
    if not resolved.is_relative_to(root.resolve()):
        raise InputError(f"{MANIFEST}: frames[{i}].file {name!r} leaves the stack folder")
    return root / rel


def _z_from_rig(rig: dict[str, Any], n: Any, i: int) -> float:
    try:
        d, d_f, step = (float(rig[k]) for k in ("d_mm", "d_f_mm", "step_mm"))
    except (KeyError, TypeError, ValueError):
        raise InputError(
            f"{MANIFEST}: frames[{i}] has no z_mm and the rig block lacks d_mm, d_f_mm, "
            "step_mm to compute it"
        ) from None
    return d - (d_f + float(n) * step)


def _depth(dtype: np.dtype) -> str:
    return {"uint8": "8-bit", "uint16": "16-bit"}.get(np.dtype(dtype).name, np.dtype(dtype).name)


def _object(doc: dict[str, Any], key: str) -> dict[str, Any]:
    value = doc.get(key)
    if value is None:
        return {}
    if not isinstance(value, dict):
        raise InputError(f"{MANIFEST}: {key!r} must be an object; got {value!r:.40}")
    return dict(value)


def _finite_number(value: Any, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InputError(f"{name} must be a number; got {value!r}")
    value = float(value)
    if not math.isfinite(value):
        raise InputError(f"{name} must be finite; got {value}")
    return value


class StackWriter:
    """Write a stack frame by frame; every frame and the manifest are written atomically.

    After :meth:`add_frame` returns, the frame file and an updated ``stack.json`` listing
    it are on disk, so a crash at any point leaves a readable stack of the frames
    completed so far (listed in acquisition order).

    Parameters
    ----------
    root : path
        The stack directory (created if missing).
    pixel_size_mm : float or None
    optics, rig, meta : dict, optional
        Stored in the manifest as they are.
    frame_format : {".png", ".tiff"}
        PNG keeps 8- and 16-bit frames losslessly; TIFF also takes float32.
    """

    def __init__(
        self,
        root: str | os.PathLike,
        *,
        pixel_size_mm: float | None,
        optics: dict[str, Any] | None = None,
        rig: dict[str, Any] | None = None,
        meta: dict[str, Any] | None = None,
        frame_format: str = ".png",
    ) -> None:
        if frame_format not in (".png", ".tiff"):
            raise InputError(f"frame_format must be '.png' or '.tiff'; got {frame_format!r}")
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)
        self.frame_format = frame_format
        self.doc: dict[str, Any] = {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION,
            "pixel_size_mm": pixel_size_mm,
            "frames": [],
            "optics": dict(optics or {}),
            "rig": dict(rig or {}),
            "meta": dict(meta or {}),
        }

    @classmethod
    def resume(cls, root: str | os.PathLike) -> "StackWriter":
        """Reopen a partly written stack; frames listed in its manifest are kept."""
        root = Path(root)
        manifest = root / MANIFEST
        if not manifest.is_file():
            raise InputError(f"nothing to resume: {manifest} does not exist")
        doc = read_json(manifest)
        if not isinstance(doc, dict) or not isinstance(doc.get("frames"), list):
            raise InputError(f"cannot resume {root}: {MANIFEST} must hold an object with a "
                             f"'frames' list; got {json.dumps(doc)[:40]}")
        for key in ("optics", "rig", "meta"):
            doc[key] = _object(doc, key)
        for i, entry in enumerate(doc["frames"]):
            if not isinstance(entry, dict) or not isinstance(entry.get("file"), str):
                raise InputError(f"cannot resume {root}: {MANIFEST} frames[{i}] must be an "
                                 "object with a 'file' string")
            _inside(root, entry["file"], i)
            _finite_number(entry.get("z_mm"), f"{MANIFEST} frames[{i}].z_mm")
        writer = cls.__new__(cls)
        writer.root = root
        writer.doc = doc
        files = [f["file"] for f in doc["frames"]]
        writer.frame_format = Path(files[0]).suffix if files else ".png"
        if writer.frame_format not in (".png", ".tiff"):
            raise InputError(f"cannot resume {root}: its frames are {writer.frame_format} "
                             "files, not written by smdinspect")
        return writer

    @property
    def frames(self) -> list[dict[str, Any]]:
        """The manifest's frame entries written so far (``file``, ``z_mm``, extras)."""
        return self.doc["frames"]

    def add_frame(self, image: np.ndarray, z_mm: float, **extra: Any) -> Path:
        """Write ``image`` (RGB or grey) as the next frame at height ``z_mm``."""
        n = len(self.doc["frames"])
        name = f"frame_{n:04d}{self.frame_format}"
        path = self.root / name
        if self.frame_format == ".tiff":
            _atomic.write_tiff(path, image)
        else:
            _atomic.write_image(path, image)
        self.doc["frames"].append({"file": name, "z_mm": float(z_mm), **extra})
        self.write_manifest()
        return path

    def write_manifest(self) -> None:
        """Rewrite ``stack.json`` atomically."""
        _atomic.write_json(self.root / MANIFEST, self.doc)
