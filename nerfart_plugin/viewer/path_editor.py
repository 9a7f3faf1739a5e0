"""The camera-path editor: keyframes from the current view, a preview, ``camera_path.json`` and a render.

Keyframes are added from the camera of the tab that clicks, shown as small frustums joined by the path
(:mod:`nerfart_plugin.viewer.keyframes`), moved to the current view or deleted by number. "Save" writes
``<run>/render/camera_paths/<name>.json`` (nerfstudio's format, the capture's world frame: the file
``stage=render render.path=<file>`` reads); "Render" writes the video where ``stage=render`` writes it
(:meth:`nerfart_plugin.api.Run.render_folder`), with a progress bar. Nothing else in the run is written.
"""

from __future__ import annotations

import logging
import re
import threading
import time
from pathlib import Path
from typing import Any, Optional

import numpy as np

from nerfart_plugin.cameras.path import read_camera_path
from nerfart_plugin.errors import NerfArtError
from nerfart_plugin.viewer.cameras import to_viser
from nerfart_plugin.viewer.keyframes import interpolate, save_path

log = logging.getLogger(__name__)


class PathEditor:
    """The path panel of ``viewer``; ``run``: the finished run to render the path of (None: save only)."""

    def __init__(self, viewer: Any, run: Optional[Any] = None) -> None:
        self.viewer, self.run = viewer, run
        self.saved: Optional[Path] = None
        self.rendered: Optional[dict] = None
        gui = viewer.server.gui
        with gui.add_folder("Camera path", expand_by_default=False):
            self.add = gui.add_button("Add keyframe", hint="add the current view as the last keyframe")
            self.which = gui.add_number("Keyframe", initial_value=1, min=1, step=1, hint="the keyframe to move/delete")
            self.move = gui.add_button("Move keyframe here")
            self.delete = gui.add_button("Delete keyframe")
            self.clear = gui.add_button("Clear path")
            self.frames = gui.add_number("Frames", initial_value=120, min=2, max=10_000, step=1)
            self.fps = gui.add_number("FPS", initial_value=24, min=1, max=240, step=1)
            self.side = gui.add_number("Resolution", initial_value=max(viewer.cams.width, viewer.cams.height),
                                       min=16, max=4096, step=1, hint="long side of the rendered video, pixels")
            self.name = gui.add_text("Name", initial_value="viewer_path")
            self.preview = gui.add_button("Preview path", hint="fly this tab's camera along the path")
            self.save = gui.add_button("Save camera_path.json", disabled=viewer.writable is None)
            self.render = gui.add_button("Render path", disabled=run is None or viewer.writable is None)
            self.progress = gui.add_progress_bar(0.0, visible=False)
            self.status = gui.add_markdown("no keyframes")
        self.add.on_click(lambda e: self._edit(lambda ks: ks.append(viewer.camera_of(e.client.camera))))
        self.move.on_click(lambda e: self._edit(lambda ks: ks.__setitem__(self._index(ks), viewer.camera_of(e.client.camera))))
        self.delete.on_click(lambda e: self._edit(lambda ks: ks.pop(self._index(ks))))
        self.clear.on_click(lambda e: self._edit(lambda ks: ks.clear()))
        self.preview.on_click(lambda e: self._fly(e.client))
        self.save.on_click(lambda e: self._guarded(self.save_file))
        self.render.on_click(lambda e: threading.Thread(target=self._guarded, args=(self.render_video,),
                                                        daemon=True).start())

    # ------------------------------------------------------------------ keyframes
    def _index(self, keyframes: list) -> int:
        i = int(self.which.value) - 1
        if not 0 <= i < len(keyframes):
            raise NerfArtError(f"keyframe {i + 1}: the path has {len(keyframes)} keyframe(s).")
        return i

    def _edit(self, change: Any) -> None:
        self._guarded(lambda: change(self.viewer.keyframes))
        self._draw()

    def _draw(self) -> None:
        scene, ks, scale = self.viewer.server.scene, self.viewer.keyframes, self.viewer.scale
        scene.remove_by_name("/path")
        for i, k in enumerate(ks):
            wxyz, pos = to_viser(k)
            scene.add_camera_frustum(f"/path/key_{i:03d}", fov=k.fov_y, aspect=k.aspect, scale=0.05 * scale,
                                     thickness=0.004 * scale, wxyz=wxyz, position=pos, color=(230, 40, 60))
        if len(ks) >= 2:
            pts = [c.c2w[:, 3] for c in interpolate(ks, max(8 * len(ks), 16))]
            scene.add_spline_catmull_rom("/path/curve", points=np.stack(pts), curve_type="catmullrom",
                                         thickness=0.005 * scale, color=(230, 40, 60))
        self.status.content = f"{len(ks)} keyframe(s)"

    # ------------------------------------------------------------------ outputs
    def _guarded(self, action: Any) -> Any:
        try:
            return action()
        except NerfArtError as exc:
            self.status.content = f"**{exc}**"
            log.warning("viewer: %s", exc)
            return None

    def _file(self) -> Path:
        name = re.sub(r"[^A-Za-z0-9_.-]+", "_", str(self.name.value)).strip("._") or "viewer_path"
        return Path(self.viewer.writable) / "camera_paths" / f"{name}.json"

    def save_file(self) -> Path:
        """Write the path as ``camera_path.json`` (see the module docstring); its path."""
        if self.viewer.writable is None:
            raise NerfArtError("this viewer has no run folder to save a camera path into.")
        out, _ = save_path(self.viewer.keyframes, self.viewer.cams, self._file(), int(self.frames.value),
                           int(self.fps.value), int(self.side.value))
        self.saved = out
        self.status.content = f"saved `{out}`"
        log.info("viewer: camera path saved to %s", out)
        return out

    def render_video(self) -> dict:
        """Save the path, then render it to the folder ``stage=render`` would use, showing progress."""

        path_file = self.save_file()
        rp = read_camera_path(path_file, self.run.cameras)
        out = self.run.render_folder(rp)
        self.progress.visible, self.progress.value = True, 0.0

        def on_frame(done: int, total: int) -> None:
            self.progress.value = 100.0 * done / max(total, 1)

        with self.viewer.field.lock:  # on the run's render thread, between two tabs' frames
            self.rendered = self.viewer.field.call(self.run.write_render, out, rp, fps=int(self.fps.value),
                                                   on_frame=on_frame)
        self.status.content = f"rendered `{self.rendered['files']['rgb']}`"
        return self.rendered

    def _fly(self, client: Any) -> None:
        """Move ``client``'s camera along the path at its frame rate (a low-resolution preview)."""
        if len(self.viewer.keyframes) < 2:
            self.status.content = "**add at least two keyframes to preview a path**"
            return
        cams = interpolate(self.viewer.keyframes, int(self.frames.value))

        def fly() -> None:
            for cam in cams:
                self.viewer.jump(client, cam)
                time.sleep(1.0 / max(float(self.fps.value), 1.0))

        threading.Thread(target=fly, name="viewer-preview", daemon=True).start()
