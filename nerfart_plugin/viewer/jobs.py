"""Render jobs: one thread per browser tab turns its latest camera into frames (the server state — camera,
panel settings — is written by viser's handlers; the thread only reads a snapshot of it).

A frame that is outdated when it finishes (the camera moved, a setting changed) is dropped, and the
schedule starts again from the fast moving frame; a closed tab stops its thread, so it costs nothing.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any, Callable, Optional

import numpy as np

from nerfart_plugin.viewer.cameras import ViewCamera
from nerfart_plugin.viewer.schedule import FrameSchedule, wait_for_share
from nerfart_plugin.viewer.sources import ViewSettings

log = logging.getLogger(__name__)


class TabRenderer:
    """Renders ``field`` for one tab and hands each frame to ``show`` ([H,W,3] uint8).

    Args:
        field: a :class:`~nerfart_plugin.viewer.sources.RunField` or ``LiveField``.
        settings: returns the panels' current :class:`ViewSettings`.
        schedule: the tab's :class:`FrameSchedule`.
        show: sends a frame to the tab (viser's background image).
    """

    def __init__(self, field: Any, settings: Callable[[], ViewSettings], schedule: FrameSchedule,
                 show: Callable[[np.ndarray], None], name: str = "tab") -> None:
        self.field, self.settings, self.schedule, self.show = field, settings, schedule, show
        self._camera: Optional[ViewCamera] = None
        self._state_changed = 0  # bumped by set_camera / refresh
        self._wake = threading.Condition()
        self._stop = False
        self.frames = 0
        self.last_frame: Optional[np.ndarray] = None
        #: the camera of the first frame sent (a new tab's view)
        self.first_camera: Optional[ViewCamera] = None
        self.last_seconds = 0.0
        self._not_before = 0.0
        self._thread = threading.Thread(target=self._loop, name=f"viewer-{name}", daemon=True)
        self._thread.start()

    # ---- written by the server's handlers
    def set_camera(self, camera: ViewCamera) -> None:
        with self._wake:
            if self._camera is not None and self._camera.key() == camera.key():
                return
            self._camera = camera
            self._state_changed += 1
            self._wake.notify()

    def refresh(self) -> None:
        """A setting or the field changed: render again from the moving frame."""
        with self._wake:
            self._state_changed += 1
            self._wake.notify()

    def stop(self) -> None:
        with self._wake:
            self._stop = True
            self._wake.notify()
        self._thread.join(timeout=10.0)

    @property
    def camera(self) -> Optional[ViewCamera]:
        """The camera the tab renders now (world frame); None before the first."""
        return self._camera

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    # ---- the job
    def _snapshot(self) -> tuple[int, Optional[ViewCamera], ViewSettings, int]:
        return self._state_changed, self._camera, self.settings(), getattr(self.field, "version", 0)

    def _loop(self) -> None:
        seen: tuple = (-1, -1)
        while True:
            with self._wake:
                while not self._stop and (self._camera is None or (self.schedule.finished and
                                                                  seen == self._seen_now())):
                    self._wake.wait(timeout=0.25)
                if self._stop:
                    return
                state, camera, settings, version = self._snapshot()
            if (state, version) != seen:
                self.schedule.restart(camera.aspect)
                seen = (state, version)
            side = self.schedule.next_side()
            if side is None:
                continue
            wait = self._not_before - time.perf_counter()
            if wait > 0:  # a live view keeps to its share of the time
                time.sleep(min(wait, 1.0))
                continue
            try:
                frame, seconds = self._render(camera, side, settings)
            except Exception:  # noqa: BLE001 - a failed frame must not end the tab's thread
                if self._stop or getattr(self.field, "closed", False):  # the viewer is closing
                    return
                log.exception("the viewer could not render a frame")
                time.sleep(1.0)
                continue
            self._not_before = time.perf_counter() + wait_for_share(seconds, getattr(self.field, "render_share", None))
            with self._wake:
                outdated = self._snapshot()[0] != state
            self.schedule.rendered(frame.shape[0] * frame.shape[1], seconds)
            if not outdated or side == self.schedule.moving_side(camera.aspect):
                self._send(frame, seconds, camera)

    def _seen_now(self) -> tuple[int, int]:
        return self._state_changed, getattr(self.field, "version", 0)

    def _render(self, camera: ViewCamera, side: int, settings: ViewSettings) -> tuple[np.ndarray, float]:
        with self.field.lock:
            return self.field.timed_render(camera, side, settings)

    def _send(self, frame: np.ndarray, seconds: float, camera: ViewCamera) -> None:
        if self.first_camera is None:
            self.first_camera = camera
        self.last_frame, self.last_seconds = frame, seconds
        self.frames += 1
        try:
            self.show(frame)
        except Exception:  # noqa: BLE001 - the tab closed while its frame was on the way
            log.debug("a frame could not be sent", exc_info=True)
