"""The viewer of a finished run: the server, its panels and the run's field put together (:func:`open_viewer`)."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Union

from nerfart_plugin.api import Run, open_run
from nerfart_plugin.viewer import panels
from nerfart_plugin.viewer.path_editor import PathEditor
from nerfart_plugin.viewer.region_panel import RegionPanel
from nerfart_plugin.viewer.server import Viewer
from nerfart_plugin.viewer.sources import RunField, sibling_runs

def open_viewer(run: Union[str, Path, Any], host: str = "127.0.0.1", port: int = 8080, device: str = "auto",
                max_side: int = 512, checkpoint: str = "final.ckpt", compile: str = "auto") -> Any:
    """Serve a finished run (a folder, a ``.ckpt`` in one, or an :class:`~nerfart_plugin.api.Run`) and return
    the running :class:`~nerfart_plugin.viewer.server.Viewer` (``.url``; ``.stop()`` to end it). ``compile``: the
    ``compile`` setting for the frames (auto: compiled in the background where a compiler is available, eager
    frames until then)."""

    opened = run if isinstance(run, Run) else open_run(run, checkpoint=checkpoint, device=device)
    siblings = sibling_runs(opened)
    field = RunField(opened, siblings, compile=compile)
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
