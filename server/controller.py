"""The quality controller of a moving view: it holds the frame time to the view's budget
by lowering the resolution scale and, once the scale is at its floor, by raising the
pixels of error. It acts on measured frame times (render and encode), not estimates.

Frame time is close to proportional to the pixel count, so the scale moves by the square
root of the time ratio. A frame over its budget brings the scale down at once by that
whole ratio (when eight viewers start together, or the budget shrinks because more views
move, damped steps would spend seconds on frames far over budget); a frame under it
raises the scale by damped, bounded steps (a frame time is noisy on a shared machine, and
a picture that grows slowly is better than one that jumps back and forth).

The budget itself is the view's share of its target interval times a gain, which the
view's measured frame rate moves: frames of several views in flight overlap, so the
share alone would hold each frame's wall time to what leaves the view at a multiple of
its target rate, at a lower resolution than the machine affords.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

MAX_STEP = 1.6  # the most the scale (or the PoE boost) changes from one frame to the next
DAMPING = 0.6  # how much of the measured correction one frame applies (in log space)
HEADROOM = 0.85  # aim a little under the budget: frames vary
POE_STEP = 1.5
SCALE_QUANTUM = 1 / 64  # scales are rounded, so near-equal frames have equal sizes
RATE_DAMPING = 0.3  # how much of a measured rate error one frame moves the budget gain


@dataclass
class QualityController:
    scale: float = 1.0
    poe_boost: float = 1.0  # the moving PoE is the chosen PoE (at least 1) times this
    # The budget's multiple of the view's share of the interval. Frames of several views
    # in flight overlap, so a frame's wall time spans the others' turns: with the share
    # alone, each of two moving views got twice its target rate at half the resolution.
    # The gain grows while the view's measured rate is over its target and shrinks when
    # under, between 1 (the share) and the frames in flight.
    gain: float = 1.0

    def moving_settings(self, base_poe: float, min_scale: float, max_poe: float) -> tuple[float, float]:
        """(resolution scale, pixels of error) for the next moving frame."""
        scale = min(1.0, max(min_scale, self.scale))
        poe = (
            base_poe
            if self.poe_boost <= 1.0
            else min(max(max_poe, base_poe), max(base_poe, 1.0) * self.poe_boost)
        )
        return scale, poe

    def observe(
        self, frame_seconds: float, budget_seconds: float, min_scale: float, max_poe: float, base_poe: float
    ) -> None:
        """Update from one moving frame that took `frame_seconds` against its budget."""
        if frame_seconds <= 0 or budget_seconds <= 0:
            return
        ratio = (HEADROOM * budget_seconds) / frame_seconds
        if ratio < 1.0:
            step = math.sqrt(ratio)  # time ~ pixels ~ scale^2: the scale that would have fitted
        else:
            step = min(MAX_STEP, math.exp(DAMPING * 0.5 * math.log(ratio)))
        if step < 1.0:
            if self.scale > min_scale + 1e-9:
                self.scale = max(min_scale, self.scale * step)
            elif max(max_poe, base_poe) > max(base_poe, 1.0) * self.poe_boost:
                self.poe_boost *= POE_STEP  # the scale is at its floor: trade accuracy instead
        else:
            if self.poe_boost > 1.0:
                if ratio > 1.3:  # get accuracy back before resolution, and only with room to spare
                    self.poe_boost = max(1.0, self.poe_boost / POE_STEP)
            else:
                self.scale = min(1.0, self.scale * step)
        self.scale = max(SCALE_QUANTUM, round(self.scale / SCALE_QUANTUM) * SCALE_QUANTUM)

    def observe_rate(self, interval_seconds: float, target_fps: float, max_gain: float) -> None:
        """Update the budget gain from the time between two moving frames of the view."""
        if interval_seconds <= 0 or target_fps <= 0:
            return
        # Aim a little over the target rate, as frame times aim a little under their budget.
        ratio = (HEADROOM / target_fps) / interval_seconds  # above 1: faster than the aim
        step = math.exp(RATE_DAMPING * math.log(min(MAX_STEP, max(1 / MAX_STEP, ratio))))
        self.gain = min(max(1.0, max_gain), max(1.0, self.gain * step))
