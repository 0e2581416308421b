"""Heights borrowed from a neighbouring edge: the small-window check and the depth-edge
mask's gap-spanning pass, on exact curves and height maps."""

import numpy as np

from smdinspect.sff import PeakTracker, borrowed_mask, depth_edge_mask


def _curves(n, peak, amp, floor=1.0, width=1.5):
    z = np.arange(n, dtype=np.float32)[:, None, None]
    return (floor + amp * np.exp(-((z - peak) ** 2) / (2 * width**2))).astype(np.float32)


def test_own_share_is_the_small_windows_focus_at_the_main_peak():
    n = 20
    # main window: peaks at frame 15 everywhere (an edge's height);
    # small window: column 0 peaks at 15 too, column 1 at frame 4 (its own texture),
    # column 2 at frame 4 but only noise-high, column 3 flat (textureless)
    main = _curves(n, np.full((1, 4), 15.0), np.full((1, 4), 50.0))
    small = np.concatenate([_curves(n, np.array([[15.0]]), np.array([[20.0]])),
                            _curves(n, np.array([[4.0]]), np.array([[20.0]])),
                            _curves(n, np.array([[4.0]]), np.array([[0.5]])),
                            np.ones((n, 1, 1), np.float32)], axis=2)
    tr = PeakTracker((1, 4), n, half_width=3)
    for i in range(n):
        tr.update(i, main[i].copy(), own=small[i].copy())
    share, ratio = tr.own_share()
    assert share[0, 0] > 0.99 and share[0, 1] < 0.01 and share[0, 2] < 0.01
    assert share[0, 3] == 1.0  # no span: nothing to say
    np.testing.assert_allclose(ratio[0, :2], 20.0, rtol=1e-3)
    flags = borrowed_mask(share, ratio, own_px=5)
    # only the clearly peaked small window that disagrees vetoes the height
    assert flags.tolist() == [[False, True, False, False]]
    # a noise pre-filter's correlated noise asks for a larger peak
    assert not borrowed_mask(share, ratio, own_px=5, noise_gain=10.0).any()


def test_depth_edge_mask_spans_a_gap_of_unreliable_pixels():
    """A low region, a gap of unreliable pixels at the step, then a band bled to the
    high side's height: the 5-px square sees no step across a 4-px gap, the wide one
    does; a steep but continuous slope is not a step in either."""
    step = 0.05
    row = np.r_[np.full(20, 0.02), np.full(4, np.nan), np.full(20, 1.2)].astype(np.float32)
    h = np.tile(row, (9, 1))
    ok = np.isfinite(h)
    h = np.nan_to_num(h)
    narrow = depth_edge_mask(h, ok, jump_mm=3 * step, radius_px=5)
    wide = depth_edge_mask(h, ok, jump_mm=3 * step, radius_px=5, wide_span_px=11)
    assert not narrow.any()
    band = wide[4]
    assert band[24:27].all()  # the high side next to the gap
    assert not band[:20].any()  # the low side keeps its heights
    assert not band[32:].any()  # beyond the radius nothing moves
    slope = np.tile(np.arange(60, dtype=np.float32) * 0.5 * step, (9, 1))  # 0.5 step/px
    assert not depth_edge_mask(slope, np.ones_like(slope, bool), jump_mm=3 * step,
                               radius_px=5, wide_span_px=11).any()


def test_depth_edge_mask_spans_a_gap_as_wide_as_the_halo_reach():
    """The halo test drops the weak texture up to halo_reach_px(11) = 12 px (a 9-px
    window's base reach, 11 px, plus its pooling) from a step's strong edge: such a gap
    hides the step from the 11-px square, not from one reaching a pixel past it each way
    (27 px), which flags the band bled to the high side; slopes of 0.5 step/px stay
    unflagged in both."""
    from smdinspect.sff._confidence import halo_reach_px

    step = 0.05
    gap = halo_reach_px(11)
    assert gap == 12
    row = np.r_[np.full(30, 0.02), np.full(gap, np.nan), np.full(30, 1.2)].astype(np.float32)
    h = np.tile(row, (31, 1))
    ok = np.isfinite(h)
    h = np.nan_to_num(h)
    spans = (11, 2 * (gap + 1) + 1)
    one = depth_edge_mask(h, ok, jump_mm=3 * step, radius_px=5, wide_span_px=11)
    two = depth_edge_mask(h, ok, jump_mm=3 * step, radius_px=5, wide_span_px=spans)
    assert not one.any()
    high = 30 + gap
    assert two[15, high:high + 3].all()
    assert not two[15, :30].any() and not two[15, high + 6:].any()
    slope = np.tile(np.arange(90, dtype=np.float32) * 0.5 * step, (31, 1))
    assert not depth_edge_mask(slope, np.ones_like(slope, bool), jump_mm=3 * step,
                               radius_px=5, wide_span_px=spans).any()


def test_depth_edge_mask_looks_across_a_gap_that_grows_with_the_step():
    """Beside a tall step the halo check's gap is wider than the 27-px square reaches
    (2·12 + 1 = 25 px here): a square of 53 px over the gap's border pixels sees both
    sides and flags the band bled to the high side; the low side keeps its heights, and
    a slope of 0.5 step/px interrupted by the same gap stays unflagged."""
    step = 0.05
    gap = 25
    row = np.r_[np.full(40, 0.02), np.full(gap, np.nan), np.full(40, 1.5)].astype(np.float32)
    h = np.tile(row, (41, 1))
    ok = np.isfinite(h)
    h = np.nan_to_num(h)
    spans = (11, 27)
    without = depth_edge_mask(h, ok, jump_mm=3 * step, radius_px=5, wide_span_px=spans)
    across = depth_edge_mask(h, ok, jump_mm=3 * step, radius_px=5, wide_span_px=spans,
                             gap_span_px=53)
    assert not without.any()
    high = 40 + gap
    assert across[20, high:high + 3].all()
    assert not across[20, :40].any() and not across[20, high + 6:].any()
    slope = np.tile(np.arange(105, dtype=np.float32) * 0.5 * step, (41, 1))
    cut = np.ones_like(slope, bool)
    cut[:, 40:40 + gap] = False
    assert not depth_edge_mask(slope, cut, jump_mm=3 * step, radius_px=5,
                               wide_span_px=spans, gap_span_px=53).any()


def _body_on_weak_board(*, board_reads, seed=10_210, step=0.05):
    """A body 10 steps tall (columns 40+) beside a board (0) whose pixels are unreliable
    but for a 4-px band at the body's foot that took the body's height (the bleed);
    the board's unreliable peaks read ``board_reads(rng, shape)`` (mm)."""
    rng = np.random.default_rng(seed)
    h = np.zeros((60, 80), np.float32)
    h[:, 40:] = 10 * step
    ok = np.zeros(h.shape, bool)
    ok[:, 36:] = True
    h[:, 36:40] = 10 * step                         # the bled band
    board = ~ok
    h[board] = board_reads(rng, h.shape)[board]
    return h, ok, step


def test_hidden_step_mask_finds_a_step_whose_low_side_is_unreliable():
    from smdinspect.sff._confidence import hidden_step_mask

    # most unreliable board peaks read the board (a quarter read noise over the sweep)
    def reads(rng, shape):
        r = rng.normal(0, 0.02, shape)
        noise = rng.random(shape) < 0.25
        return np.where(noise, rng.uniform(0, 0.6, shape), r).astype(np.float32)

    h, ok, step = _body_on_weak_board(board_reads=reads)
    # the reliable heights alone show no step: the ordinary check flags nothing
    assert not depth_edge_mask(h, ok, jump_mm=3 * step, radius_px=5).any()
    flag = hidden_step_mask(h, ok, np.ones_like(ok), jump_mm=3 * step, radius_px=5, side_px=13)
    assert flag[8:-8, 36:38].all()  # the band's outer columns (the corners: too few in the square)
    assert not flag[:, 46:].any()                     # beyond the radius: kept
    assert not flag[~ok].any()                        # only reliable pixels are judged


def test_hidden_step_mask_needs_most_unreliable_neighbours_to_read_lower():
    from smdinspect.sff._confidence import hidden_step_mask

    # a plateau running on into weak texture at its own height (the peaks read it)
    h, ok, step = _body_on_weak_board(
        board_reads=lambda rng, shape: rng.normal(0.5, 0.02, shape).astype(np.float32))
    assert not hidden_step_mask(h, ok, np.ones_like(ok), jump_mm=3 * step, radius_px=5,
                                side_px=13).any()
    # noise peaks spread over the whole sweep: fewer than half lie 3 steps below
    h, ok, step = _body_on_weak_board(
        board_reads=lambda rng, shape: rng.uniform(0, 1.0, shape).astype(np.float32))
    assert not hidden_step_mask(h, ok, np.ones_like(ok), jump_mm=3 * step, radius_px=5,
                                side_px=13).any()
    # too few unreliable pixels in the square (a small hole): nothing told
    h, ok, step = _body_on_weak_board(
        board_reads=lambda rng, shape: np.zeros(shape, np.float32))
    ok[:, :36] = True
    ok[30:33, 33:36] = False                         # 9 pixels: under a quarter of 13²
    assert not hidden_step_mask(h, ok, np.ones_like(ok), jump_mm=3 * step, radius_px=5,
                                side_px=13).any()
    # pixels not ``measured`` (weak texture: their peaks are noise) are no evidence
    h, ok, step = _body_on_weak_board(
        board_reads=lambda rng, shape: np.zeros(shape, np.float32))
    assert hidden_step_mask(h, ok, np.ones_like(ok), jump_mm=3 * step, radius_px=5,
                            side_px=13).any()
    assert not hidden_step_mask(h, ok, ok.copy(), jump_mm=3 * step, radius_px=5,
                                side_px=13).any()
