"""When a browser tab gets which frame: a fast low-resolution frame while its camera moves, refined when it
rests, and a cap on the share of time a live (training) view may take.

The low-resolution frame's size is not fixed: it is chosen from the field's measured speed (rays per
second) so that it takes about ``moving_seconds`` whatever the run (a converged balanced run renders
several times more rays per second than an unconverged draft run with a coarse occupancy grid). Once
the camera rests, the frame is rendered again at each larger size of ``refine_sides`` in turn.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional


@dataclass
class FrameSchedule:
    """The frame sizes of one tab.

    Attributes:
        refine_sides: long sides (pixels) rendered in turn once the camera rests, ascending; the last is the
            finest frame (the capture's size or the viewer's cap).
        moving_seconds: the time a frame may take while the camera moves (seconds).
        min_side / max_moving_side: bounds (pixels, long side) of the moving frame.
        rays_per_second: the measured speed (exponential average over rendered frames); None before the first.
    """

    refine_sides: tuple[int, ...] = (256,)
    moving_seconds: float = 0.08
    min_side: int = 32
    max_moving_side: int = 160
    rays_per_second: Optional[float] = None
    _level: int = field(default=0, repr=False)
    _ladder: tuple[int, ...] = field(default=(), repr=False)

    def restart(self, aspect: float = 1.0) -> None:
        """The camera moved (or the field changed): start again from the moving frame."""
        moving = self.moving_side(aspect)
        self._ladder = (moving, *[s for s in sorted(set(self.refine_sides)) if s > moving])
        self._level = 0

    def moving_side(self, aspect: float = 1.0) -> int:
        """Long side (pixels) of a frame that takes about ``moving_seconds`` at the measured speed
        (before any measurement: twice ``min_side``), never above the finest frame."""
        top = min(self.max_moving_side, max(self.refine_sides, default=self.max_moving_side))
        if not self.rays_per_second:
            return min(2 * self.min_side, top)
        short_per_long = min(aspect, 1.0 / aspect) if aspect > 0 else 1.0
        side = math.sqrt(self.rays_per_second * self.moving_seconds / max(short_per_long, 1e-3))
        return int(min(max(side, self.min_side), top))

    def next_side(self) -> Optional[int]:
        """The long side of the next frame to render, or None when the finest one has been rendered."""
        if not self._ladder:
            self.restart()
        return self._ladder[self._level] if self._level < len(self._ladder) else None

    def rendered(self, rays: int, seconds: float) -> None:
        """A frame of ``rays`` pixels took ``seconds``: update the speed and move up one size."""
        if seconds > 0 and rays > 0:
            rate = rays / seconds
            self.rays_per_second = rate if self.rays_per_second is None else 0.5 * (self.rays_per_second + rate)
        self._level += 1

    @property
    def finished(self) -> bool:
        return self.next_side() is None


def wait_for_share(seconds_rendered: float, share: Optional[float]) -> float:
    """Seconds to wait after a frame that took ``seconds_rendered`` so that rendering takes at most
    ``share`` of the wall time (None or >= 1: no wait). A live view uses it to bound what it costs training."""
    if share is None or share >= 1.0:
        return 0.0
    share = max(share, 1e-3)
    return seconds_rendered * (1.0 - share) / share
