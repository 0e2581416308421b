"""Cameras: folder replay, OpenCV capture (from a real video file), averaging, errors."""

from __future__ import annotations

import sys

import cv2
import numpy as np
import pytest

from smdinspect._atomic import write_image
from smdinspect.acquire import (
    Camera,
    FolderCamera,
    GenICamCamera,
    OpenCVCamera,
    capture_average,
)
from smdinspect.errors import CameraError

from .conftest import make_frames


def test_folder_camera_replays_in_name_order_and_seeks(tmp_path):
    frames = make_frames(tmp_path, 5)
    (tmp_path / "notes.txt").write_text("not an image")
    (tmp_path / ".img_999.png").write_bytes(b"hidden temp file")
    with FolderCamera(tmp_path) as cam:
        for i in range(3):
            img, meta = cam.capture()
            np.testing.assert_array_equal(img, frames[i])
            assert meta == {"source": f"img_{i:03d}.png"}
        cam.seek(4)
        np.testing.assert_array_equal(cam.capture()[0], frames[4])
        with pytest.raises(CameraError, match="ran out of images after 5 captures"):
            cam.capture()
    looped = FolderCamera(tmp_path, loop=True)
    looped.open()
    looped.seek(6)
    np.testing.assert_array_equal(looped.capture()[0], frames[1])


def test_folder_camera_errors(tmp_path):
    with pytest.raises(CameraError, match="directory .*nope not found"):
        FolderCamera(tmp_path / "nope").open()
    with pytest.raises(CameraError, match="no images in"):
        FolderCamera(tmp_path).open()
    (tmp_path / "a.png").write_bytes(b"\x89PNG\r\n\x1a\n truncated")
    with pytest.raises(CameraError, match="folder camera: frame .*a.png is truncated"):
        FolderCamera(tmp_path).capture()


def test_capture_average_rounds_back_to_dtype(tmp_path):
    write_image(tmp_path / "a.png", np.full((4, 5), 10, np.uint8))
    write_image(tmp_path / "b.png", np.full((4, 5), 13, np.uint8))
    img, meta = capture_average(FolderCamera(tmp_path), 2)
    assert img.dtype == np.uint8 and np.all(img == 12)  # rint(11.5) = 12
    assert meta["n_averaged"] == 2 and meta["source"] == "a.png"
    write_image(tmp_path / "c.png", np.zeros((4, 6), np.uint8))
    cam = FolderCamera(tmp_path)
    cam.seek(1)
    with pytest.raises(CameraError, match=r"capture 2 of 2 is \(4, 6\) uint8; the first was "
                                          r"\(4, 5\) uint8"):
        capture_average(cam, 2)


def test_camera_rejects_bad_arrays():
    class Bad(Camera):
        def capture(self):
            from smdinspect.acquire._camera import _check_frame

            return _check_frame(np.zeros((4, 4), np.int64), "bad camera"), {}

    with pytest.raises(CameraError, match="pixels of type int64"):
        Bad().capture()


@pytest.fixture
def video(tmp_path):
    """A real 8-frame MJPG video: OpenCV's VideoCapture plays it like a camera."""
    path = tmp_path / "cam.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (80, 64))
    if not writer.isOpened():
        pytest.fail("OpenCV cannot write an MJPG test video in this build")
    for i in range(8):
        bgr = np.zeros((64, 80, 3), np.uint8)
        bgr[:, :, 2] = 200  # red in BGR order
        bgr[:, :, 0] = 20 * i  # blue grows frame by frame
        writer.write(bgr)
    writer.release()
    return path


def test_opencv_camera_captures_rgb_and_grey(video):
    with OpenCVCamera(str(video), width=80, height=64, warmup_frames=0, flush_frames=0) as cam:
        img, meta = cam.capture()  # open() consumed frame 0 checking the size
        assert img.shape == (64, 80, 3) and img.dtype == np.uint8
        assert abs(int(img[..., 0].mean()) - 200) <= 4  # red channel first: RGB
        assert abs(int(img[..., 2].mean()) - 20) <= 4  # frame 1: blue = 20
        assert meta["device"] == str(video)
    with OpenCVCamera(str(video), grey=True, warmup_frames=2, flush_frames=1) as cam:
        img, _ = cam.capture()
        assert img.shape == (64, 80)


def test_opencv_camera_errors(video):
    with pytest.raises(CameraError, match="camera '/dev/no-such-video' not found or busy"):
        OpenCVCamera("/dev/no-such-video").open()
    with pytest.raises(CameraError, match="delivers 80x64 px frames; the rig file asks for "
                                          "640x480"):
        OpenCVCamera(str(video), width=640, height=480, warmup_frames=0).open()
    cam = OpenCVCamera(str(video), warmup_frames=0, flush_frames=0)
    cam.open()
    for _ in range(7):
        cam.capture()
    with pytest.raises(CameraError, match="returned no frame"):
        cam.capture()  # the "camera" was unplugged: the video ended
    cam.close()


def test_genicam_without_harvesters_is_a_clear_camera_error(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "harvesters", None)  # not installed
    monkeypatch.setitem(sys.modules, "harvesters.core", None)
    with pytest.raises(CameraError, match=r"optional 'harvesters' package: pip install "
                                          r"'smdinspect\[genicam\]'"):
        GenICamCamera(tmp_path / "producer.cti").open()
