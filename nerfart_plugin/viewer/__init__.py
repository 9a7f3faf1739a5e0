"""A live web viewer of radiance fields (viser): fly through a finished run, dial the style, lay a camera path,
or watch a run train.

    python -m nerfart_plugin.viewer outputs/stylizations/<run>          # serves http://127.0.0.1:8080
    python -m nerfart_plugin guidance=imagenet +prompt=Joker viewer.live=true   # watch the training

The page opens on the capture's front camera and renders the field from the browser's camera: a fast
low-resolution frame while the camera moves, refined once it rests (:mod:`~nerfart_plugin.viewer.schedule`).
Panels: the channel, source | stylized | split, the strength dial and the mix weights of other
stylizations of the same source, a region box to style inside only and save
(:mod:`~nerfart_plugin.viewer.region_panel`), the capture's cameras (click one to jump there), the run's mesh,
the run's facts, and the camera-path editor (:mod:`~nerfart_plugin.viewer.path_editor`). Each browser tab keeps
its own camera. The viewer binds 127.0.0.1 unless told otherwise and only reads the run folder (the path
editor writes under ``<run>/render``, the region panel under ``<run>/regions``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Union

from nerfart_plugin.api import Run, open_run
from nerfart_plugin.viewer import panels
from nerfart_plugin.viewer.path_editor import PathEditor
from nerfart_plugin.viewer.region_panel import RegionPanel
from nerfart_plugin.viewer.server import Viewer
from nerfart_plugin.viewer.sources import RunField, sibling_runs

__all__ = ["open_viewer"]


def open_viewer(run: Union[str, Path, Any], host: str = "127.0.0.1", port: int = 8080, device: str = "auto",
                max_side: int = 512, checkpoint: str = "final.ckpt") -> Any:
    """Serve a finished run (a folder, a ``.ckpt`` in one, or an :class:`~nerfart_plugin.api.Run`) and return
    the running :class:`~nerfart_plugin.viewer.server.Viewer` (``.url``; ``.stop()`` to end it)."""

    opened = run if isinstance(run, Run) else open_run(run, checkpoint=checkpoint, device=device)
    siblings = sibling_runs(opened)
    field = RunField(opened, siblings)
    viewer = Viewer(field, host=host, port=port, max_side=max_side, writable=Path(opened.folder) / "render",
                    title=f"nerfart_plugin: {opened.metrics.get('prompt') or opened.kind}")
    panels.add_facts(viewer, panels.run_facts(opened))
    viewer.panels["view"] = panels.add_view_panel(viewer, field.is_stylization)
    if field.is_stylization:
        viewer.panels["style"] = panels.add_style_panel(viewer, siblings)
        viewer.panels["region"] = RegionPanel(viewer, Path(opened.folder))
    viewer.panels["mesh"] = panels.add_mesh_toggle(viewer, panels.run_mesh(opened.folder, opened.kind))
    viewer.path_editor = PathEditor(viewer, opened)
    capture = panels.CaptureFrustums(viewer)
    viewer.photos_loading = panels.load_photos_later(opened, capture)
    return viewer
