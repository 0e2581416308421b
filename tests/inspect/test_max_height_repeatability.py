"""Repeatability of the max joint height (issue 13, gauge R&R goal).

A gauge R&R study re-places one board between sweeps: the solder stays, the placement
and the sensor noise change. Here the same synthetic board (one seed, so the same
fillets) is rendered at a few placements, reconstructed by shape from focus and measured
with the known placement (no registration: that keeps the tests fast and leaves the
estimators as the only thing that varies). The gull-wing heel fillet, fitted along the
foot, must vary less between sweeps than the percentile of the foot it replaced, and
stay accurate; the chips' meniscus fit keeps its spread.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from smdinspect.inspect import InspectConfig, load_board
from smdinspect.inspect._measure import (
    MeasureContext,
    _heel_beyond_knee,
    _heel_fillet,
    footprints,
    measure_board,
)
from smdinspect.optics import Optics
from smdinspect.pipeline import inspection_focus_config
from smdinspect.sff import reconstruct
from smdinspect.synth import board_scene, render_stack
from smdinspect.synth._render import SensorConfig

DEMO = "references/demo_board.json"
STEP_MM = 0.05
P_MM = 0.02
#: Re-placements within the simulator's range (±2 mm, ±5°), as (dx, dy, rotation).
PLACEMENTS = ((0.3, -0.2, 3.7), (-0.4, 0.1, -3.7), (0.1, 0.4, -1.6), (-0.2, -0.3, 2.4))


#: Boards (seeds) the sweeps are rendered of: one board's readings are one draw of its
#: textures and fillets, and a bound that held for one board failed for another (seed 3
#: read the heels' σ 8.1 µm where seed 2 read 4.3 µm).
BOARD_SEEDS = (2, 3, 4)


@pytest.fixture(scope="module")
def gullwing_sweeps(tmp_path_factory):
    return _boards(tmp_path_factory.mktemp("gw"), "U1", (3.4, 4.2), (330, 330))


@pytest.fixture(scope="module")
def chip_sweeps(tmp_path_factory):
    return _boards(tmp_path_factory.mktemp("chip"), "R3", (7.4, 8.95), (110, 190))


def _boards(root, ref, centre_mm, shape):
    """:func:`_measured` of every board of ``BOARD_SEEDS``, keyed ``seed:joint``."""
    return {f"{seed}:{jid}": v for seed in BOARD_SEEDS
            for jid, v in _measured(root / f"b{seed}", ref, centre_mm, shape,
                                    board_seed=seed).items()}


def _measured(root, ref, centre_mm, shape, *, board_seed: int):
    """Per joint of ``ref``, over the sweeps: (max_mm, foot_mm, true height) arrays and
    the max methods."""
    board = load_board(DEMO)
    part = board.component(ref)
    cfg = InspectConfig()
    out: dict[str, list] = {}
    for k in range(len(PLACEMENTS)):
        dx, dy, rot = PLACEMENTS[k]
        a = math.radians(rot)
        R = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
        off = -R @ (np.asarray(centre_mm) - np.asarray(board.size_mm) / 2) + [dx, dy]
        scene, labels = board_scene(board, pixel_size_mm=P_MM, seed=board_seed, shape=shape,
                                    offset_mm=tuple(off), rotate_deg=rot)
        lo, hi = scene.height_range_mm()
        z = np.round(np.arange(hi + 3 * STEP_MM, lo - 3 * STEP_MM, -STEP_MM), 6)
        stack = render_stack(scene, z, optics=Optics.for_pixel_size(P_MM),
                             sensor=SensorConfig.preset("normal"), seed=100 * board_seed + k,
                             out=root / f"s{k}", previews=False)
        s = reconstruct(stack, inspection_focus_config())
        T = np.array(labels["placement"]["board_to_world"])
        height = np.asarray(s.height_mm, np.float64)
        reliable = np.asarray(s.reliable, bool) & np.isfinite(height)
        ctx = MeasureContext(height=height, reliable=reliable,
                             u_px=np.full(height.shape, np.nan), bare=reliable, T=T, p=P_MM,
                             u_plane_mm=0.0)
        occupied = np.zeros(height.shape, bool)
        for m in footprints(board, ctx, margin_px=0.1 / P_MM).values():
            occupied |= m
        ctx.bare = reliable & ~occupied & (np.abs(height) <= 0.06)
        # Only the part in the crop is measured (the others lie outside the image).
        joints, _ = measure_board(dataclasses.replace(board, components=(part,)), ctx, cfg)
        truth = {j["id"]: j["true_height_mm"] for j in labels["joints"]}
        for j in part.joints:
            m = joints[j.id]
            out.setdefault(j.id, []).append((m.max_mm, m.foot_mm, truth[j.id], m.max_method))
    return {k: (np.array([v[0] for v in vs]), np.array([v[1] for v in vs]),
                np.array([v[2] for v in vs]), [v[3] for v in vs]) for k, vs in out.items()}


def _pooled_sd(arrays) -> float:
    """√(mean within-joint variance) over joints (each array: one joint's sweeps)."""
    return float(np.sqrt(np.mean([np.var(a, ddof=1) for a in arrays])))


def test_heel_fillet_more_repeatable_than_the_foot_percentile(gullwing_sweeps):
    # The heel fillet is read on the foot. A few readings fall to the side strip: since
    # the centroid correction takes its gradient from the pixel's own level (no longer
    # across the unmeasured wall between the lead's top and the pad), a steep side fillet
    # reads near pad level, and U1.2 at the fourth placement reads ~50 µm there on every
    # board (a false `insufficient`: README, weak spots); 7 of the 96 readings here.
    methods = [m for v in gullwing_sweeps.values() for m in v[3]]
    assert len(methods) == 96 and sum(m != "foot" for m in methods) <= 8, methods
    foot = {k: np.array(v[3]) == "foot" for k, v in gullwing_sweeps.items()}
    maxes = [v[0][foot[k]] for k, v in gullwing_sweeps.items() if foot[k].sum() >= 2]
    feet = [v[1][foot[k]] for k, v in gullwing_sweeps.items() if foot[k].sum() >= 2]
    sd_fit, sd_pct = _pooled_sd(maxes), _pooled_sd(feet)
    # SOIC-8 band 130-572 µm: 10 % GR&R is σ = 7.4 µm. Here the fit reads 6.6 µm pooled
    # over the three boards, the foot's percentile (the max height before) 9.5 µm.
    assert sd_fit <= 7.4e-3, (sd_fit, sd_pct)
    assert sd_fit < 0.8 * sd_pct, (sd_fit, sd_pct)
    err = np.concatenate([(v[0] - v[2])[foot[k]] for k, v in gullwing_sweeps.items()])
    assert abs(float(np.mean(err))) <= 0.008, err
    assert float(np.max(np.abs(err))) <= 0.025, err


def test_chip_meniscus_spread_bounded(chip_sweeps):
    maxes = [v[0] for v in chip_sweeps.values()]
    assert all(np.isfinite(m).all() for m in maxes)
    # 0603 band 336 µm: 10 % GR&R is σ = 5.6 µm; the meniscus fit reads 3.2 µm here,
    # pooled over the three boards (4.3, 2.2, 2.6 µm; with the texture drawn in image
    # coordinates, not fixed to the board: 4.6, 7.3, 5.6 µm).
    assert _pooled_sd(maxes) <= 5.0e-3, maxes


def _foot_profile(rng, *, lead=0.23, top=0.29, reach=0.3, length=0.84, knee_um=15.0,
                  noise_um=4.0, dropout=0.4):
    """A heel fillet along a foot as shape from focus sees it: correlated noise, holes,
    and the knee's blurred edge raising the first pixels next to the heel."""
    import cv2

    xs = np.arange(0.0, length, P_MM)
    rows = 19
    x = np.repeat(xs[None, :], rows, axis=0)
    z = lead + (top - lead) * np.clip(1 - x / reach, 0, None) ** 2
    n = cv2.GaussianBlur(rng.standard_normal(x.shape).astype(np.float32), (0, 0), 1.2)
    z = z + n * (noise_um * 1e-3 / max(float(n.std()), 1e-9))
    knee = rng.uniform(0, knee_um * 1e-3, rows)[:, None] * np.exp(-x / 0.02)
    z = z + knee
    keep = rng.random(x.shape) >= dropout
    return x[keep], z[keep]


@pytest.mark.parametrize("knee_um, max_bias_um", [(0.0, 2.0), (15.0, 6.0)])
def test_heel_fillet_on_noisy_profiles_beats_the_percentile(knee_um, max_bias_um):
    rng = np.random.default_rng(13)
    fit, pct = [], []
    for _ in range(30):
        x, z = _foot_profile(rng, knee_um=knee_um)
        lead = float(np.median(z[x >= 0.42]))
        h, u = _heel_fillet(x, z, np.full(z.shape, 1e-3), lead, foot_length_mm=0.84,
                            pixel_size_mm=P_MM)
        assert np.isfinite(h) and u > 0
        fit.append(h)
        pct.append(float(np.percentile(z, 97)))
    fit, pct = np.array(fit), np.array(pct)
    # Unbiased without the knee's blur (the percentile of a thinning fillet reads low),
    # and less spread than the percentile either way.
    assert abs(fit.mean() - 0.29) <= max_bias_um * 1e-3, fit.mean()
    assert abs(fit.mean() - 0.29) < abs(pct.mean() - 0.29) or knee_um > 0
    assert fit.std() <= 0.85 * pct.std(), (fit.std(), pct.std())


def test_heel_fillet_flat_foot_and_buried_foot():
    rng = np.random.default_rng(5)
    # No solder above the lead: the fit stays at the lead's top.
    x, z = _foot_profile(rng, top=0.23, knee_um=0.0, noise_um=2.0)
    h, _ = _heel_fillet(x, z, np.full(z.shape, np.nan), float(np.median(z)),
                        foot_length_mm=0.84, pixel_size_mm=P_MM)
    assert abs(h - 0.23) <= 0.004
    # Solder burying the foot (excess): high everywhere, highest at the heel.
    xs = np.repeat(np.arange(0.0, 0.84, P_MM)[None, :], 15, axis=0).ravel()
    zs = 0.45 - 0.06 * xs / 0.84 + rng.normal(0, 0.002, xs.shape)
    h, _ = _heel_fillet(xs, zs, np.full(zs.shape, np.nan), float(np.median(zs[xs >= 0.42])),
                        foot_length_mm=0.84, pixel_size_mm=P_MM)
    assert 0.43 <= h <= 0.47
    # Too few pixels: NaN, never a guess.
    h, u = _heel_fillet(np.array([0.0, 0.02]), np.array([0.3, 0.3]), np.array([1e-3, 1e-3]),
                        0.23, foot_length_mm=0.84, pixel_size_mm=P_MM)
    assert math.isnan(h) and math.isnan(u)


def test_the_knees_blend_on_a_dry_heel_is_not_borne_out_beyond_its_reach():
    """Shape from focus blends the knee's edge into the foot's first pixels (half the
    focus window and a bit: ``mixing_mm``): on a dry heel they rise like a meniscus
    ~0.1 mm long, which the fit along the whole foot reads as a heel fillet. Beyond the
    mixing reach the foot stays at the lead's top: the fit there does not bear it out.
    A real heel fillet (reach 0.3 mm) is borne out within a few µm."""
    rng = np.random.default_rng(21)
    mixing = 0.09  # (5 // 2 + 2) px at 20 µm/px
    blends, fillets = [], []
    for _ in range(10):
        x, z = _foot_profile(rng, top=0.23, knee_um=0.0, noise_um=2.0, dropout=0.3)
        z = z + 0.045 * np.clip(1 - x / 0.1, 0, None) ** 2      # the knee's blend
        lead = float(np.median(z[x >= 0.42]))
        full, _ = _heel_fillet(x, z, np.full(z.shape, 1e-3), lead, foot_length_mm=0.84,
                               pixel_size_mm=P_MM)
        assert full > 0.23 + 0.02, full     # read as a fillet along the whole foot
        blends.append(_heel_beyond_knee(x, z, np.full(z.shape, 1e-3), lead,
                                        foot_length_mm=0.84, pixel_size_mm=P_MM,
                                        mixing_mm=mixing)[0])
        x, z = _foot_profile(rng, knee_um=15.0, noise_um=2.0, dropout=0.3)
        lead = float(np.median(z[x >= 0.42]))
        top, u = _heel_beyond_knee(x, z, np.full(z.shape, 1e-3), lead, foot_length_mm=0.84,
                                   pixel_size_mm=P_MM, mixing_mm=mixing)
        assert 0 < u < 0.006, u
        fillets.append(top)
    assert max(blends) <= 0.23 + 0.01, blends
    assert all(abs(f - 0.29) <= 0.012 for f in fillets), fillets
    # No focus window (true heights) or too few pixels beyond the reach: no evidence.
    for mixing in (0.0, 0.83):
        assert all(map(math.isnan, _heel_beyond_knee(
            x, z, np.full(z.shape, 1e-3), lead, foot_length_mm=0.84, pixel_size_mm=P_MM,
            mixing_mm=mixing)))
