"""The viewer's server: one viser server, the shared panel state, and a render job per browser tab.

Server state (what the panels set: channel, view, weights; the keyframes) lives here and is shared by
all tabs; each tab keeps its own camera and its own :class:`~nerfart_plugin.viewer.jobs.TabRenderer`.
The page shows the capture's world frame: the field as the background image of each tab, the
training cameras as frustums (click one to jump there), the run's mesh on demand, the keyframes.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import replace
from pathlib import Path
from typing import Any, Optional

import numpy as np

from nerfart_plugin.cameras.capture import front_camera
from nerfart_plugin.data.normalize import look_at_centre
from nerfart_plugin.viewer.cameras import ViewCamera, capture_camera, from_viser, scene_scale, to_viser
from nerfart_plugin.viewer.jobs import TabRenderer
from nerfart_plugin.viewer.schedule import FrameSchedule
from nerfart_plugin.viewer.sources import ViewSettings

log = logging.getLogger(__name__)

#: the finest frame the viewer renders by default (long side, pixels; the capture's size when smaller)
DEFAULT_MAX_SIDE = 512
#: JPEG quality of the frames sent to the browser
JPEG_QUALITY = 90


class Viewer:
    """A running viewer of ``field`` (:mod:`nerfart_plugin.viewer.sources`).

    Args:
        field: what is rendered; host / port: where to serve (port 0: any free port).
        max_side: the finest frame's long side (pixels); the capture's own size when smaller.
        writable: the folder the path editor may write into (``<run>/render``); None: no saving.
        title: the label at the top of the panel.
    """

    def __init__(self, field: Any, host: str = "127.0.0.1", port: int = 8080, max_side: int = DEFAULT_MAX_SIDE,
                 writable: Optional[Path] = None, title: str = "nerfart_plugin") -> None:
        import viser

        self.field = field
        self.cams = field.cameras
        self.settings = ViewSettings()
        self.writable = writable
        native = max(self.cams.width, self.cams.height)
        self.refine_sides = tuple(sorted({min(256, native), min(native, max_side)}))
        self.tabs: dict[int, TabRenderer] = {}
        self.keyframes: list[ViewCamera] = []
        #: called with each new tab's client (per-tab scene nodes: the capture's frustums)
        self.tab_hooks: list[Any] = []
        self.close_hooks: list[Any] = []
        self.panels: dict[str, Any] = {}
        self._lock = threading.Lock()
        self.server = viser.ViserServer(host=host, port=port, label=title, verbose=False)
        self.front_index = self._front_index()
        self.front = capture_camera(self.cams, self.front_index)
        self._place_scene()
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(self._disconnect)

    # ------------------------------------------------------------------ where it is
    @property
    def host(self) -> str:
        return self.server.get_host()

    @property
    def port(self) -> int:
        return self.server.get_port()

    @property
    def url(self) -> str:
        host = self.host
        return f"http://{'127.0.0.1' if host in ('0.0.0.0', '') else host}:{self.port}"

    def _front_index(self) -> int:
        return front_camera(self.cams.to_world(self.cams.c2w[:, :3, :4]))

    def _place_scene(self) -> None:
        """Up direction and the camera a new tab opens on: the capture's front camera."""
        world = self.cams.to_world(self.cams.c2w[:, :3, :4])
        up = -world[:, :3, 1].mean(0)
        up = up / max(np.linalg.norm(up), 1e-12)
        self.up, self.centre, self.scale = up, look_at_centre(world), scene_scale(self.cams)
        self.server.scene.set_up_direction(tuple(up))
        init = self.server.initial_camera
        init.position = tuple(self.front.c2w[:, 3])
        init.look_at = tuple(self.centre)
        init.up = tuple(up)
        init.fov = float(self.front.fov_y)

    # ------------------------------------------------------------------ tabs
    def _connect(self, client: Any) -> None:
        schedule = FrameSchedule(refine_sides=self.refine_sides)

        def show(frame: np.ndarray) -> None:
            client.scene.set_background_image(frame, format="jpeg", jpeg_quality=JPEG_QUALITY)

        tab = TabRenderer(self.field, lambda: self.settings, schedule, show, name=str(client.client_id))
        with self._lock:
            self.tabs[client.client_id] = tab

        @client.camera.on_update
        def _(camera: Any) -> None:
            tab.set_camera(self.camera_of(camera))

        # a new tab reports the browser's default camera before it adopts the initial one: open on the front camera
        tab.set_camera(replace(self.front, aspect=self.camera_of(client.camera).aspect))
        for hook in self.tab_hooks:
            hook(client)
        log.info("viewer: tab %s connected", client.client_id)

    def _disconnect(self, client: Any) -> None:
        with self._lock:
            tab = self.tabs.pop(client.client_id, None)
        if tab is not None:
            tab.stop()
        for hook in self.close_hooks:
            hook(client.client_id)
        log.info("viewer: tab %s closed", client.client_id)

    @staticmethod
    def camera_of(camera: Any) -> ViewCamera:
        """A viser camera handle as a :class:`ViewCamera` (world frame)."""
        aspect = camera.image_width / camera.image_height if camera.image_height else camera.aspect
        return from_viser(camera.wxyz, camera.position, camera.fov, aspect)

    def jump(self, client: Any, camera: ViewCamera) -> None:
        """Move ``client``'s browser camera to ``camera`` (looking at the capture's centre distance)."""
        wxyz, position = to_viser(camera)
        with client.atomic():
            client.camera.wxyz = wxyz
            client.camera.position = position
            client.camera.fov = camera.fov_y

    # ------------------------------------------------------------------ shared settings
    def update(self, **changes: Any) -> None:
        """Change the shared :class:`ViewSettings` and render every tab again."""
        self.settings = replace(self.settings, **changes)
        self.refresh_tabs()

    def refresh_tabs(self) -> None:
        with self._lock:
            tabs = list(self.tabs.values())
        for tab in tabs:
            tab.refresh()

    def stop(self) -> None:
        with self._lock:
            tabs, self.tabs = list(self.tabs.values()), {}
        for tab in tabs:
            tab.stop()
        if hasattr(self.field, "close"):
            self.field.close()
        self.server.stop()
