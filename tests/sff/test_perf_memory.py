"""reconstruct() streams: its peak memory does not grow with the number of frames."""

import tracemalloc

import cv2
import numpy as np

from smdinspect.sff import FocusConfig, reconstruct
from smdinspect.stack import FocalStack, StackWriter


def _cone_stack(root, n_frames, size=96):
    rng = np.random.default_rng(0)
    tex = cv2.GaussianBlur(rng.random((size, size), dtype=np.float32), (0, 0), 1.0)
    tex = (tex - tex.mean()) / tex.std()
    yy, xx = np.mgrid[:size, :size] - size / 2
    height = np.clip(1.0 - np.hypot(xx, yy) / (0.45 * size), 0, None)
    writer = StackWriter(root, pixel_size_mm=0.01)
    for n, z in enumerate(np.linspace(-0.1, 1.1, n_frames)):
        sigma = np.clip(np.abs(height - z) * 8.0, 0.3, 6.0)
        img = np.zeros((size, size), np.float32)
        for s in np.unique(np.round(sigma, 1)):  # blur by level, pick per pixel
            sel = np.round(sigma, 1) == s
            img[sel] = cv2.GaussianBlur(tex, (0, 0), float(s))[sel]
        img = 128 + 40 * img + rng.normal(0, 1.0, img.shape)
        writer.add_frame(np.clip(img, 0, 255).astype(np.uint8), float(z))
    return FocalStack.open(root)


def _peak_bytes(stack, config):
    reconstruct(stack, config)  # warm caches (noise tables, imports)
    tracemalloc.start()
    try:
        reconstruct(stack, config)
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def test_peak_memory_is_flat_in_the_number_of_frames(tmp_path):
    config = FocusConfig(workers=2)
    few = _peak_bytes(_cone_stack(tmp_path / "few", 12), config)
    many = _peak_bytes(_cone_stack(tmp_path / "many", 60), config)
    # 5x the frames: a stack held in memory would need ~5x; streaming stays within noise
    assert many <= 1.25 * few, (few, many)


def test_alignment_pass_memory_is_flat_in_the_number_of_frames(tmp_path):
    config = FocusConfig(workers=2, align=True)
    few = _peak_bytes(_cone_stack(tmp_path / "few", 12), config)
    many = _peak_bytes(_cone_stack(tmp_path / "many", 60), config)
    # the alignment pre-pass caches decoded frames only up to FRAME_CACHE_BYTES
    assert many <= 1.25 * few, (few, many)
