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


def share_a_machine(views: int, in_flight: int, frames: int, adapt_gain: bool) -> tuple[float, float]:
    """`views` moving views of equal cost take turns on one machine with `in_flight`
    frames at once: a frame's wall time is its own render time times the frames in flight
    (it waits for the others' turns), and so is the time between two of a view's frames.
    Returns (scale, frames/s per view) after `frames` frames each."""
    c = QualityController()
    fps = 16.0
    for _ in range(frames):
        _, poe = c.moving_settings(1.0, 0.1, 8)
        wall = frame_seconds(c, poe) * min(in_flight, views)
        budget = min(c.gain, in_flight) / (fps * views)
        c.observe(wall, budget, 0.1, 8, 1.0)
        if adapt_gain:
            c.observe_rate(wall, fps, in_flight)
    return c.scale, 1.0 / (frame_seconds(c, 1.0) * min(in_flight, views))


def test_views_sharing_in_flight_frames_get_their_rate_at_a_sharper_scale() -> None:
    """Two views, two frames in flight: budgeting each view's share of the interval alone
    gives each twice its target rate at 1/sqrt(2) of the scale it could have; the rate
    gain brings the rate down to (a little over) the target and the scale up."""
    fixed_scale, fixed_fps = share_a_machine(2, 2, 80, adapt_gain=False)
    scale, fps = share_a_machine(2, 2, 80, adapt_gain=True)
    assert fixed_fps > 1.5 * 16.0
    assert 16.0 <= fps <= 16.0 / HEADROOM * 1.1  # a little over the target, as budgets aim under
    assert scale > 1.3 * fixed_scale


def test_the_rate_gain_stays_between_one_and_the_frames_in_flight() -> None:
    c = QualityController()
    for _ in range(50):
        c.observe_rate(0.01, 16.0, 3)  # far faster than 16 frames/s
    assert c.gain == pytest.approx(3.0)
    for _ in range(50):
        c.observe_rate(1.0, 16.0, 3)  # far slower
    assert c.gain == 1.0
    c.observe_rate(0.0, 16.0, 3)  # no interval: no change
    assert c.gain == 1.0
