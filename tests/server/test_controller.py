"""The moving-view quality controller on a model of frame time (seconds proportional to
the pixel count): a frame far over budget brings the scale down at once to what fits;
under budget the scale climbs back in bounded steps to full resolution; at the scale's
floor it trades accuracy (PoE) instead, and gets it back first when there is room."""

from __future__ import annotations

import itertools
import math

import pytest

from vastray.server.controller import HEADROOM, MAX_STEP, QualityController

FULL_FRAME = 0.25  # seconds for a full-resolution frame


def frame_seconds(c: QualityController, poe: float, base_poe: float = 1.0) -> float:
    # Raising the PoE makes frames cheaper (fewer, coarser LOD nodes).
    return FULL_FRAME * c.scale**2 * (base_poe / poe) ** 0.5


def run(c: QualityController, budget: float, frames: int, min_scale: float = 0.1, max_poe: float = 8) -> None:
    for _ in range(frames):
        scale, poe = c.moving_settings(1.0, min_scale, max_poe)
        assert scale == c.scale or scale == min_scale
        c.observe(frame_seconds(c, poe), budget, min_scale, max_poe, 1.0)


def test_one_frame_over_budget_brings_the_scale_to_what_fits() -> None:
    c = QualityController()
    budget = FULL_FRAME / 30  # eight viewers sharing two cores, say
    run(c, budget, 1)
    assert frame_seconds(c, 1.0) <= budget * 1.05
    assert c.scale == pytest.approx(math.sqrt(HEADROOM / 30), abs=1 / 64)


def test_under_budget_the_scale_climbs_in_bounded_steps_to_full() -> None:
    c = QualityController(scale=0.2)
    scales = [c.scale]
    for _ in range(20):
        run(c, FULL_FRAME * 4, 1)
        scales.append(c.scale)
    steps = [b / a for a, b in itertools.pairwise(scales) if b > a]
    assert steps and max(steps) <= MAX_STEP + 1 / 64 / min(scales)
    assert scales[-1] == 1.0 and scales[1] < 0.5, "climbs, not jumps"


def test_at_the_floor_the_poe_is_raised_then_given_back_first() -> None:
    c = QualityController()
    run(c, FULL_FRAME * 0.1**2 / 4, 6, min_scale=0.1)  # even the floor is 4x over budget
    assert c.scale == pytest.approx(0.1, abs=1 / 64) and c.poe_boost > 1.0
    _, poe = c.moving_settings(1.0, 0.1, 8.0)
    assert 1.0 < poe <= 8.0
    run(c, FULL_FRAME * 2, 40, min_scale=0.1)  # room again: accuracy back before resolution
    assert c.poe_boost == 1.0 and c.scale == 1.0
