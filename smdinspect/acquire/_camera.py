"""Cameras behind one interface: ``capture() -> (frame, metadata)``.

* :class:`OpenCVCamera` - USB/UVC cameras (and anything ``cv2.VideoCapture`` opens);
* :class:`FolderCamera` - replays a directory of images in name order;
* :class:`SimulatedCamera` - renders a synthetic scene at the z the stage reports;
* :class:`GenICamCamera` - GigE Vision / USB3 Vision cameras through the optional
  ``harvesters`` package (``pip install 'smdinspect[genicam]'``).

Frames are ``(H, W)`` grey or ``(H, W, 3)`` RGB arrays of ``uint8``, ``uint16`` or
``float32``, as the device delivers them (never rescaled). :func:`capture_average`
averages N captures to cut noise.
"""

from __future__ import annotations

import logging
import os
import time
from abc import ABC, abstractmethod
from pathlib import Path
from typing import Any, Callable

import numpy as np

from ..errors import CameraError, InputError

__all__ = [
    "Camera",
    "FolderCamera",
    "GenICamCamera",
    "OpenCVCamera",
    "SimulatedCamera",
    "capture_average",
]

log = logging.getLogger(__name__)


class Camera(ABC):
    """A source of frames. Use as a context manager (``open`` / ``close``)."""

    def open(self) -> None:  # noqa: B027 - optional hook
        """Acquire the device."""

    def close(self) -> None:  # noqa: B027 - optional hook
        """Release the device (never raises)."""

    @abstractmethod
    def capture(self) -> tuple[np.ndarray, dict[str, Any]]:
        """Take one frame.

        Returns
        -------
        frame : (H, W) or (H, W, 3) uint8, uint16 or float32
            RGB channel order for colour.
        metadata : dict
            JSON-serialisable facts about the frame (exposure, gain, source file, ...).

        Raises
        ------
        CameraError
            No frame could be taken.
        """

    def seek(self, capture_index: int) -> None:  # noqa: B027 - optional hook
        """Say which capture of the sweep comes next (counted from 0).

        Replayed and simulated cameras use it to continue an interrupted sweep exactly
        where it stopped; live cameras ignore it.
        """

    def __enter__(self) -> "Camera":
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def capture_average(camera: Camera, n: int = 1) -> tuple[np.ndarray, dict[str, Any]]:
    """Capture ``n`` frames and return their mean (noise falls as 1/sqrt(n)).

    Integer frames are averaged in float64 and rounded back to their dtype; float32
    stays float32. The metadata is the first capture's, with ``"n_averaged": n``.

    Raises
    ------
    CameraError
        The ``n`` captures differ in shape or dtype.
    """
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise InputError(f"frames per step must be an integer >= 1; got {n!r}")
    first, meta = camera.capture()
    first = np.asarray(first)
    if n == 1:
        return first, dict(meta)
    acc = first.astype(np.float64)
    for k in range(1, n):
        frame, _ = camera.capture()
        frame = np.asarray(frame)
        if frame.shape != first.shape or frame.dtype != first.dtype:
            raise CameraError(f"capture {k + 1} of {n} is {frame.shape} {frame.dtype}; the first "
                              f"was {first.shape} {first.dtype}")
        acc += frame
    acc /= n
    if np.issubdtype(first.dtype, np.integer):
        info = np.iinfo(first.dtype)
        out = np.clip(np.rint(acc), info.min, info.max).astype(first.dtype)
    else:
        out = acc.astype(first.dtype)
    return out, {**meta, "n_averaged": n}


def _check_frame(frame: Any, source: str) -> np.ndarray:
    img = np.asarray(frame)
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] != 3) or img.size == 0:
        raise CameraError(f"{source} delivered an array of shape {img.shape}; expected (H, W) "
                          "or (H, W, 3)")
    if img.dtype not in (np.uint8, np.uint16, np.float32):
        raise CameraError(f"{source} delivered pixels of type {img.dtype}; expected uint8, "
                          "uint16 or float32")
    return img


# ---------------------------------------------------------------------------------------
class OpenCVCamera(Camera):
    """A camera opened with ``cv2.VideoCapture`` (USB/UVC webcams, microscopes, ...).

    Parameters
    ----------
    device : int or str
        Device index (``0``), device path (``/dev/video2``) or a stream URL.
    width, height : int, optional
        Requested frame size in px; checked after opening.
    exposure : float, optional
        ``CAP_PROP_EXPOSURE`` in the backend's unit (V4L2: 100 µs steps; DirectShow:
        log2 seconds, e.g. -6); auto exposure is switched off first. A camera that
        refuses is logged, not fatal.
    gain : float, optional
        ``CAP_PROP_GAIN``.
    grey : bool
        Convert to one channel (focus measures work on grey anyway).
    warmup_frames : int
        Frames read and dropped after opening (auto-exposure settling).
    flush_frames : int
        Frames grabbed and dropped before each capture, so a frame buffered while the
        stage was still moving is never used.
    """

    def __init__(self, device: int | str = 0, *, width: int | None = None,
                 height: int | None = None, exposure: float | None = None,
                 gain: float | None = None, grey: bool = False, warmup_frames: int = 5,
                 flush_frames: int = 1) -> None:
        if isinstance(device, bool) or not isinstance(device, (int, str)):
            raise InputError(f"camera device must be an index or a path/URL; got {device!r}")
        for name, value in (("width", width), ("height", height)):
            if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value <= 0):
                raise InputError(f"camera {name} must be a positive integer; got {value!r}")
        for name, value in (("warmup_frames", warmup_frames), ("flush_frames", flush_frames)):
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise InputError(f"camera {name} must be an integer >= 0; got {value!r}")
        self.device, self.width, self.height = device, width, height
        self.exposure, self.gain, self.grey = exposure, gain, bool(grey)
        self.warmup_frames, self.flush_frames = warmup_frames, flush_frames
        self._cap = None

    def open(self) -> None:
        import cv2

        cap = cv2.VideoCapture(self.device)
        if not cap.isOpened():
            cap.release()
            raise CameraError(f"camera {self.device!r} not found or busy (OpenCV could not open "
                              "it; check the device index/path and that no other program uses it)")
        self._cap = cap
        if self.width:
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, self.width)
        if self.height:
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, self.height)
        if self.exposure is not None:
            # V4L2 takes 1 = manual; some backends take 0.25 = manual.
            if not cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, 1):
                cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, 0.25)
            if not cap.set(cv2.CAP_PROP_EXPOSURE, float(self.exposure)):
                log.warning("camera %r does not support setting the exposure", self.device)
        if self.gain is not None and not cap.set(cv2.CAP_PROP_GAIN, float(self.gain)):
            log.warning("camera %r does not support setting the gain", self.device)
        for _ in range(self.warmup_frames):
            cap.read()
        frame, _ = self.capture()
        h, w = frame.shape[:2]
        if (self.width and w != self.width) or (self.height and h != self.height):
            self.close()
            raise CameraError(f"camera {self.device!r} delivers {w}x{h} px frames; the rig file "
                              f"asks for {self.width or w}x{self.height or h}")

    def close(self) -> None:
        cap, self._cap = self._cap, None
        if cap is not None:
            cap.release()

    def capture(self) -> tuple[np.ndarray, dict[str, Any]]:
        import cv2

        if self._cap is None:
            raise CameraError(f"camera {self.device!r} is not open")
        for _ in range(self.flush_frames):
            self._cap.grab()
        ok, frame = self._cap.read()
        if not ok or frame is None:
            raise CameraError(f"camera {self.device!r} returned no frame (unplugged?)")
        if frame.ndim == 3:
            code = cv2.COLOR_BGR2GRAY if self.grey else cv2.COLOR_BGR2RGB
            frame = cv2.cvtColor(frame, code)
        meta = {"device": self.device, "time_s": time.time()}
        for key, prop in (("exposure", cv2.CAP_PROP_EXPOSURE), ("gain", cv2.CAP_PROP_GAIN)):
            value = self._cap.get(prop)
            if np.isfinite(value):
                meta[key] = float(value)
        return _check_frame(frame, f"camera {self.device!r}"), meta


# ---------------------------------------------------------------------------------------
class FolderCamera(Camera):
    """Replays the images of a directory in name order, one per capture.

    Parameters
    ----------
    path : path
        Directory of ``.png``/``.tif``/``.jpg``/``.bmp`` files.
    loop : bool
        Start again at the first image after the last (default: error).
    """

    def __init__(self, path: str | os.PathLike, *, loop: bool = False) -> None:
        self.path = Path(path)
        self.loop = bool(loop)
        self.files: list[Path] = []
        self._next = 0

    def open(self) -> None:
        from ..stack import IMAGE_SUFFIXES

        if not self.path.is_dir():
            raise CameraError(f"folder camera: directory {self.path} not found")
        self.files = sorted(p for p in self.path.iterdir()
                            if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
                            and not p.name.startswith("."))
        if not self.files:
            raise CameraError(f"folder camera: no images in {self.path}")

    def seek(self, capture_index: int) -> None:
        self._next = int(capture_index)

    def capture(self) -> tuple[np.ndarray, dict[str, Any]]:
        from ..stack import read_image

        if not self.files:
            self.open()
        i = self._next
        if i >= len(self.files):
            if not self.loop:
                raise CameraError(f"folder camera ran out of images after {len(self.files)} "
                                  f"captures ({self.path})")
            i %= len(self.files)
        path = self.files[i]
        self._next += 1
        try:
            frame = read_image(path)
        except InputError as exc:
            raise CameraError(f"folder camera: {exc}") from None
        return _check_frame(frame, f"folder camera ({path.name})"), {"source": path.name}


# ---------------------------------------------------------------------------------------
class SimulatedCamera(Camera):
    """Renders a synthetic :class:`~smdinspect.synth.Scene` at the stage's z.

    Parameters
    ----------
    scene : smdinspect.synth.Scene
    optics : smdinspect.optics.Optics
        Its object pixel must equal the scene's ``pixel_size_mm``.
    z_source : callable () -> float
        Returns the focused-plane height ``z_mm`` now. The rig passes a function that
        queries the stage and maps the machine z it reports, so a frame shows what a real
        camera would see where the stage actually is.
    sensor : smdinspect.synth.SensorConfig, optional
        Default: the renderer's default (noisy) sensor.
    seed : int
        Noise seed. The first capture at a height ``z`` uses the renderer's per-frame
        generator ``frame_rng(seed, z)``, so it is byte-identical to frame ``z`` of
        ``render_stack(..., seed=seed)`` and to the same capture in a resumed sweep.
        Further captures at the same height (``frames_per_step`` > 1) draw fresh noise
        from ``default_rng([seed, round(z·1e6), repeat])``.
    """

    def __init__(self, scene: Any, *, optics: Any, z_source: Callable[[], float],
                 sensor: Any = None, seed: int = 0) -> None:
        if not callable(z_source):
            raise InputError("z_source must be a callable returning the focused-plane z_mm")
        if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
            raise InputError(f"seed must be an integer >= 0; got {seed!r}")
        self.scene, self.optics, self.sensor = scene, optics, sensor
        self.z_source, self.seed = z_source, seed
        self._last_z_nm: int | None = None
        self._repeat = 0

    def render(self, z_mm: float, repeat: int = 0) -> np.ndarray:
        """The frame of the ``repeat``-th capture (from 0) with the focus at ``z_mm``."""
        from ..synth import render_frame

        z_nm = int(round(float(z_mm) * 1e6))
        rng: Any = self.seed if repeat == 0 else np.random.default_rng(
            [self.seed, abs(z_nm), int(z_nm < 0), repeat])
        return render_frame(self.scene, float(z_mm), optics=self.optics, sensor=self.sensor,
                            rng=rng)

    def capture(self) -> tuple[np.ndarray, dict[str, Any]]:
        z = float(self.z_source())
        z_nm = int(round(z * 1e6))
        self._repeat = self._repeat + 1 if z_nm == self._last_z_nm else 0
        self._last_z_nm = z_nm
        frame = self.render(z, self._repeat)
        return _check_frame(frame, "simulated camera"), {"z_rendered_mm": z,
                                                          "repeat": self._repeat}


# ---------------------------------------------------------------------------------------
class GenICamCamera(Camera):
    """A GenICam camera (GigE Vision, USB3 Vision) through ``harvesters``.

    Parameters
    ----------
    cti : path
        The GenTL producer (``.cti``) of the camera vendor's SDK.
    serial_number : str, optional
        Which camera; the first one found when omitted.
    exposure_us : float, optional
        ``ExposureTime`` node (µs).
    gain_db : float, optional
        ``Gain`` node (dB).
    timeout_s : float
        Longest wait for one frame.
    """

    def __init__(self, cti: str | os.PathLike, *, serial_number: str | None = None,
                 exposure_us: float | None = None, gain_db: float | None = None,
                 timeout_s: float = 5.0) -> None:
        self.cti = Path(cti)
        self.serial_number = serial_number
        self.exposure_us, self.gain_db, self.timeout_s = exposure_us, gain_db, float(timeout_s)
        self._harvester = None
        self._ia = None

    def open(self) -> None:
        try:
            from harvesters.core import Harvester
        except ImportError:
            raise CameraError(
                "GenICam cameras need the optional 'harvesters' package: "
                "pip install 'smdinspect[genicam]' (and your vendor's GenTL producer .cti)"
            ) from None
        if not self.cti.is_file():
            raise CameraError(f"GenTL producer file {self.cti} not found")
        h = Harvester()
        h.add_file(str(self.cti))
        h.update()
        if not h.device_info_list:
            h.reset()
            raise CameraError(f"no GenICam camera found through {self.cti.name}")
        try:
            search = {"serial_number": self.serial_number} if self.serial_number else None
            ia = h.create(search) if search else h.create()
        except Exception as exc:  # noqa: BLE001 - harvesters raises assorted errors
            h.reset()
            raise CameraError(f"cannot open GenICam camera {self.serial_number or '(first)'}: "
                              f"{exc}") from None
        nodes = ia.remote_device.node_map
        for node, value in (("ExposureTime", self.exposure_us), ("Gain", self.gain_db)):
            if value is not None:
                try:
                    getattr(nodes, node).value = float(value)
                except Exception as exc:  # noqa: BLE001
                    log.warning("GenICam camera refuses %s=%s: %s", node, value, exc)
        ia.start()
        self._harvester, self._ia = h, ia

    def close(self) -> None:
        ia, h = self._ia, self._harvester
        self._ia = self._harvester = None
        try:
            if ia is not None:
                ia.stop()
                ia.destroy()
        finally:
            if h is not None:
                h.reset()

    def capture(self) -> tuple[np.ndarray, dict[str, Any]]:
        if self._ia is None:
            raise CameraError("GenICam camera is not open")
        try:
            with self._ia.fetch(timeout=self.timeout_s) as buffer:
                comp = buffer.payload.components[0]
                data = np.array(comp.data, copy=True)
                h, w = int(comp.height), int(comp.width)
                fmt = str(getattr(comp.data_format, "value", comp.data_format))
        except Exception as exc:  # noqa: BLE001
            raise CameraError(f"GenICam camera returned no frame: {exc}") from None
        channels = data.size // (h * w)
        frame = data.reshape(h, w, channels) if channels > 1 else data.reshape(h, w)
        if frame.dtype not in (np.uint8, np.uint16):
            frame = frame.astype(np.uint16)
        return _check_frame(frame, "GenICam camera"), {"pixel_format": fmt,
                                                        "exposure_us": self.exposure_us,
                                                        "gain_db": self.gain_db}
