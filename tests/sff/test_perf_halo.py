"""The sorted, shared-grouping halo search equals the per-pixel reference it replaced."""

import cv2
import numpy as np
import pytest

from smdinspect.sff._confidence import defocus_halo_mask, halo_mask


def _reference_halo_mask(amplitude, frame_pos, candidate, *, radius_px, min_frames=2.0,
                         ratio=4.0):
    """halo_mask as it was before the speed-up (commit 424390d)."""
    h, w = amplitude.shape
    s = max(1, radius_px // 4)
    hs, ws = -(-h // s), -(-w // s)
    rs = max(1, radius_px // s)
    disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * rs + 1, 2 * rs + 1))
    bins = np.clip(np.round(np.nan_to_num(frame_pos, nan=0.0, posinf=0.0, neginf=0.0)), 0,
                   None).astype(np.int32)  # a non-finite position is bin 0
    nb = int(bins.max()) + 1
    gap = max(1, int(np.ceil(min_frames)))
    strong = np.where(candidate, amplitude, 0).astype(np.float32).ravel()
    order = np.argsort(bins.ravel(), kind="stable")
    starts = np.searchsorted(bins.ravel()[order], np.arange(nb + 1))
    members = [order[starts[b]:starts[b + 1]] for b in range(nb)]
    cell = ((np.arange(h) // s)[:, None] * ws + (np.arange(w) // s)[None, :]).ravel()
    has_candidate = [bool(strong[m].any()) for m in members]

    def spread(b):
        pooled = np.zeros(hs * ws, np.float32)
        np.maximum.at(pooled, cell[members[b]], strong[members[b]])
        return cv2.dilate(pooled.reshape(hs, ws), disk).ravel()

    dom = np.zeros(h * w, np.float32)
    for bins_in_order in (range(nb), range(nb - 1, -1, -1)):
        running = np.zeros(hs * ws, np.float32)
        pending = []
        for b in bins_in_order:
            pending.append(spread(b) if has_candidate[b] else None)
            if len(pending) > gap:
                done = pending.pop(0)
                if done is not None:
                    np.maximum(running, done, out=running)
            m = members[b]
            if m.size:
                dom[m] = np.maximum(dom[m], running[cell[m]])
    return dom.reshape(h, w) > ratio * amplitude


def _scene(seed, shape=(157, 203), n_frames=13):
    rng = np.random.default_rng(seed)
    amp = (rng.gamma(0.6, 1.0, shape) * rng.random(shape) ** 3).astype(np.float32)
    amp[rng.random(shape) < 0.2] = 0
    pos = rng.uniform(-0.4, n_frames - 0.6, shape)
    pos[rng.random(shape) < 0.01] = np.nan
    cand = rng.random(shape) < 0.4
    return amp, pos, cand


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("radius_px, min_frames, ratio", [(3, 2, 4.0), (11, 3, 2.0),
                                                          (40, 5, 9.5), (1, 1, 1.0)])
def test_halo_mask_equals_reference(seed, radius_px, min_frames, ratio):
    amp, pos, cand = _scene(seed)
    got = halo_mask(amp, pos, cand, radius_px=radius_px, min_frames=min_frames, ratio=ratio)
    want = _reference_halo_mask(amp, pos, cand, radius_px=radius_px, min_frames=min_frames,
                                ratio=ratio)
    assert got.dtype == bool and got.shape == amp.shape
    assert np.array_equal(got, want)


@pytest.mark.parametrize("kappa", [0.0, 0.7, 6.0])
def test_defocus_halo_mask_equals_reference(kappa):
    amp, pos, cand = _scene(5, n_frames=21)
    kwargs = dict(base_radius_px=11, ratio=4.0, n_frames=21, power=2.0)
    got = defocus_halo_mask(amp, pos, cand, blur_px_per_frame=kappa, **kwargs)
    want = np.zeros(amp.shape, bool)
    last = -1
    for g in (2, 3, 5, 8, 13):
        radius = int(min(max(11, min(amp.shape) // 4), max(11, round(2 * kappa * g))))
        if radius == last and g != 2:
            continue
        want |= _reference_halo_mask(amp, pos, cand, radius_px=radius, min_frames=g,
                                     ratio=4.0 * (g / 2) ** 2)
        last = radius
    assert np.array_equal(got, want)


def _reference_unsupported_mask(height_mm, reliable, *, distance_px, tol_mm):
    """unsupported_mask as it was before the speed-up (commit 424390d)."""
    h, w = height_mm.shape
    d = int(distance_px)
    half = max(1, d // 2)
    supported = np.zeros((h, w), bool)
    hv = np.where(reliable, height_mm, np.nan).astype(np.float32)
    offsets = {(sy * a, sx * b) for a, b in ((d, 0), (0, d), (d, d), (d, half), (half, d))
               for sy in (-1, 1) for sx in (-1, 1)}
    for dy, dx in sorted(offsets):
        ys, yd = slice(max(0, -dy), h - max(0, dy)), slice(max(0, dy), h - max(0, -dy))
        xs, xd = slice(max(0, -dx), w - max(0, dx)), slice(max(0, dx), w - max(0, -dx))
        with np.errstate(invalid="ignore"):
            supported[ys, xs] |= np.abs(hv[ys, xs] - hv[yd, xd]) <= tol_mm
    return reliable & ~supported


@pytest.mark.parametrize("distance_px, tol_mm", [(9, 0.05), (1, 0.2), (5, np.float64(0.1)),
                                                 (14, 0.3)])
def test_unsupported_mask_equals_reference(distance_px, tol_mm):
    from smdinspect.sff._confidence import unsupported_mask

    rng = np.random.default_rng(distance_px)
    height = np.cumsum(rng.normal(0, 0.05, (97, 131)), axis=1).astype(np.float32)
    height[rng.random(height.shape) < 0.05] += 1.0
    reliable = rng.random(height.shape) < 0.7
    got = unsupported_mask(height, reliable, distance_px=distance_px, tol_mm=tol_mm)
    want = _reference_unsupported_mask(height, reliable, distance_px=distance_px, tol_mm=tol_mm)
    assert np.array_equal(got, want)


@pytest.mark.parametrize("radius_px", [3, 16, 23, 45, 60])
def test_dilate_disc_equals_opencv_disc(radius_px):
    """The disc dilation as a union of separable rectangles equals OpenCV's elliptic
    kernel pixel for pixel, borders included (sparse finite levels in a −inf map)."""
    from smdinspect.sff._confidence import dilate_disc

    rng = np.random.default_rng(radius_px)
    level = rng.random((211, 307)).astype(np.float32)
    level[level < 0.995] = -np.inf
    disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius_px + 1,) * 2)
    want = cv2.dilate(level, disk, borderType=cv2.BORDER_REPLICATE)
    assert np.array_equal(dilate_disc(level, radius_px), want)


@pytest.mark.parametrize("radius_px", [5, 15, 45])
@pytest.mark.parametrize("where", ["inside", "corner", "none"])
def test_dilate_disc_of_a_few_steps_equals_opencv_disc(radius_px, where):
    """Only the steps' bounding box grown by the radius is dilated: the same as OpenCV's
    elliptic kernel over the whole map, wherever the steps lie (away from the borders,
    at a corner, none at all)."""
    from smdinspect.sff._confidence import dilate_disc

    rng = np.random.default_rng(radius_px)
    level = np.full((240, 310), -np.inf, np.float32)
    rows, cols = {"inside": (slice(100, 130), slice(140, 150)),
                  "corner": (slice(0, 6), slice(300, 310)), "none": (slice(0, 0),) * 2}[where]
    block = level[rows, cols]
    block[rng.random(block.shape) < 0.2] = rng.random(1).astype(np.float32)
    disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius_px + 1,) * 2)
    want = cv2.dilate(level, disk, borderType=cv2.BORDER_REPLICATE)
    assert np.array_equal(dilate_disc(level, radius_px), want)


def test_depth_edge_mask_with_levels_given_is_the_same():
    from smdinspect.sff._confidence import depth_edge_mask, step_levels

    rng = np.random.default_rng(3)
    h = np.where(rng.random((120, 160)) < 0.01, 1.0, 0.0).astype(np.float32)
    h = cv2.GaussianBlur(h, (0, 0), 2.0) * np.float32(40)
    ok = rng.random(h.shape) < 0.8
    levels = step_levels(h, ok, jump_mm=0.15, span_px=5)
    kept = levels.copy()
    for radius_px, wide in ((5, 11), (15, 0), (45, 0)):
        want = depth_edge_mask(h, ok, jump_mm=0.15, radius_px=radius_px, wide_span_px=wide)
        assert want.any()
        got = depth_edge_mask(h, ok, jump_mm=0.15, radius_px=radius_px, wide_span_px=wide,
                              levels=levels)
        assert np.array_equal(got, want)
    assert np.array_equal(levels, kept)  # not modified
