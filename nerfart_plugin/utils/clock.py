"""Wall seconds of the named parts of a job (a stage's fit, evaluation, video, meshes; an export's parts)."""

from __future__ import annotations

import time
from contextlib import contextmanager
from typing import Iterator


class PartClock:
    """Wall seconds per named part (``seconds``, summed over repeats of a part) and since the clock was made
    (:meth:`total`), so that a user sees where the time went."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self.started = time.perf_counter()

    @contextmanager
    def part(self, name: str) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] = round(self.seconds.get(name, 0.0) + time.perf_counter() - t0, 3)

    def total(self) -> float:
        """Seconds since the clock was made."""
        return time.perf_counter() - self.started
