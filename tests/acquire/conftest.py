"""Fixtures: a fake GRBL controller on a real pty, a stage talking to it, small images."""

from __future__ import annotations

import numpy as np
import pytest

from smdinspect._atomic import write_image
from smdinspect.acquire import FakeGrbl, GrblStage, StageConfig

FAST = dict(steps_per_mm=400.0, max_rate_mm_s=200.0)


def stage_config(**kw) -> StageConfig:
    """A config for the fake: no boot wait, short time-outs, fast polling."""
    base = dict(fake=True, boot_wait_s=0.0, timeout_s=0.5, move_timeout_s=5.0,
                poll_interval_s=0.002, feed_mm_min=12000.0, z_min_mm=-20.0, z_max_mm=0.0)
    base.update(kw)
    return StageConfig(**base)


@pytest.fixture
def fake():
    with FakeGrbl(start_z_mm=-1.0, **FAST) as f:
        yield f


@pytest.fixture
def stage(fake):
    st = GrblStage(stage_config(), port=fake.port)
    st.open()
    yield st
    st.close()


def make_frames(folder, n, *, shape=(48, 64), seed=0):
    """``n`` distinct random grey PNGs named in order; returns the arrays."""
    rng = np.random.default_rng(seed)
    frames = []
    for i in range(n):
        img = rng.integers(0, 256, size=shape, dtype=np.uint8)
        write_image(folder / f"img_{i:03d}.png", img)
        frames.append(img)
    return frames


@pytest.fixture
def frames_dir(tmp_path):
    d = tmp_path / "frames"
    d.mkdir()
    make_frames(d, 12)
    return d
